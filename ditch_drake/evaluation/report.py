"""The results page: success rates with Wilson intervals, failures, Figure 5-style plots.

`write_report(results, out_md, figures_dir)` reads every results file (JSON Lines from
`evaluate` / `experiment`), keeps the current records of each (`load_report_data`), groups
them by study, and writes a Markdown page with

- one table per study: model, environment, successes / trials, rate and 95 % Wilson
  interval, failures by status and region;
- figures in the style of the paper's Figure 5 (PNG, matplotlib), each with a caption
  under it: (a-d) per environment, success against the number of demonstrations
  (scalability) beside the other environments' models in it (generalization); (e) the
  learned policy against the DWA baseline per environment; (f) the amalgam model against
  the single-environment models in the amalgam's evaluation environment; and for any
  other results file, its success rate per model and environment;
- the paper's stated findings (SPEC "Experiments") beside ours, each marked as agreeing or
  not by a rule computed from the numbers, never by hand.

A study is recognized from a results file's name (`scalability.jsonl`, ...); any other
file gets a table and a bar chart of its own, under its name. The findings table is
written when at least one of the paper's studies is present.

Only the current records count (`results.current_records`): one per rollout key (a real
outcome beats an error record), and per learned checkpoint name only the records of the
file as it is now where it still resolves. What was set aside is said on the page.

`default_outputs` names where `ditch-drake report` writes by default: beside the results,
never into the tracked docs/ (`tracked_by_git` lets the command refuse to overwrite a
tracked file it was not told to).
"""

import math
import os
import re
import subprocess
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from ditch_drake.common.files import atomic_output, atomic_write_text, remove_stale_temporaries
from ditch_drake.evaluation.results import RolloutRecord, current_records, read_records
from ditch_drake.evaluation.summary import AROUND_TILT_DEG, GroupSummary, summarize

STUDIES = ("scalability", "generalization", "baseline", "amalgam")
# What each kind of bar is drawn as (colour, hatch), so the figures agree with each other.
_OWN_MODEL = {"color": "tab:blue"}
_OTHER_MODELS = {"color": "tab:gray"}
_BASELINE = {"color": "tab:red"}
_AMALGAM = {"color": "tab:orange", "hatch": "xx", "edgecolor": "black"}
_AROUND = {"fill": False, "hatch": "///", "edgecolor": "black", "linewidth": 0.0}
_AROUND_LABEL = f"successes that went around the ditch (peak tilt < {AROUND_TILT_DEG:g} deg)"
_CI_TEXT = "Error bars: 95 % Wilson score intervals"


def model_label(record: RolloutRecord) -> str:
    """A short name of the controller: the checkpoint's file stem, or the controller."""
    return Path(record.checkpoint).stem if record.checkpoint else record.controller


def model_demos(label: str) -> int | None:
    """N of a model named `<envs>_<N>` (as the experiment names them), else None."""
    tail = label.rsplit("_", 1)[-1]
    return int(tail) if tail.isdigit() else None


def model_environments(label: str) -> list[str]:
    return label.rsplit("_", 1)[0].split("+") if model_demos(label) is not None else [label]


def default_outputs(results: list[str | os.PathLike]) -> tuple[Path, Path]:
    """Where `ditch-drake report` writes by default: beside the first results entry.

    A folder `results/paper` gives `results/paper/report.md`; a file `results/x.jsonl` gives
    `results/x_report.md`. The figures go to the page's name with `_img` beside it
    (`results/paper/report_img/`, `results/x_report_img/`).
    """
    first = Path(results[0])
    out = first / "report.md" if first.is_dir() else first.with_name(f"{first.stem}_report.md")
    return out, figures_beside(out)


def figures_beside(out: str | os.PathLike) -> Path:
    """The default figures folder of a page: `<page name>_img` beside it."""
    out = Path(out)
    return out.with_name(f"{out.stem}_img")


def tracked_by_git(path: str | os.PathLike) -> bool:
    """Whether git tracks `path` (for a folder: any file under it). Not a git checkout, or no
    git on this machine: False."""
    path = Path(os.path.abspath(path))
    existing = next(folder for folder in [path, *path.parents] if folder.is_dir())
    try:
        result = subprocess.run(["git", "-C", str(existing), "ls-files", "--error-unmatch", "--",
                                 os.path.relpath(path, existing)], capture_output=True, timeout=30, check=False)
    except (OSError, subprocess.SubprocessError):
        return False
    return result.returncode == 0


@dataclass
class ReportData:
    """What a results page summarises.

    Attributes:
        records: the current records of each study (results file name), in file order.
        notes: what was set aside or could not be read, one sentence each.
        summaries: per study, a `GroupSummary` per (model, environment).
        tables: per study, its Markdown table's lines.
    """

    records: dict[str, list[RolloutRecord]]
    notes: list[str] = field(default_factory=list)
    summaries: dict[str, dict[tuple[str, str], GroupSummary]] = field(default_factory=dict)
    tables: dict[str, list[str]] = field(default_factory=dict)

    @property
    def studies(self) -> list[str]:
        """The paper's studies present, in the paper's order, then the other files' names."""
        return [*(study for study in STUDIES if study in self.records), *sorted(set(self.records) - set(STUDIES))]

    def markdown_tables(self) -> str:
        """Every study's table under its name (what `ditch-drake report` prints)."""
        return "\n".join(f"## {study}\n\n" + "\n".join(self.tables[study]) + "\n" for study in self.studies)


def load_by_study(results: list[str | os.PathLike]) -> dict[str, list[RolloutRecord]]:
    """Records per results file name (a study's, or any other), from files or folders of them."""
    return _read_by_study(results, [])


def _read_by_study(results: list[str | os.PathLike], notes: list[str]) -> dict[str, list[RolloutRecord]]:
    by_study: dict[str, list[RolloutRecord]] = defaultdict(list)
    for entry in results:
        entry = Path(entry)
        for file in sorted(entry.glob("*.jsonl")) if entry.is_dir() else [entry]:
            records, warnings = read_records(file)
            by_study[file.stem] += records
            notes += warnings
    return dict(by_study)


def checkpoint_digests(records: list[RolloutRecord]) -> dict[str, str]:
    """The digest of each learned checkpoint name in `records` whose file resolves now (by
    `learning.checkpoint.checkpoint_digest`; a name that resolves to no file is left out)."""
    from ditch_drake.learning.checkpoint import checkpoint_digest

    digests = {}
    for name in sorted({record.checkpoint for record in records if record.checkpoint}):
        try:
            digests[name] = checkpoint_digest(name)
        except OSError:
            pass
    return digests


def load_report_data(results: list[str | os.PathLike]) -> ReportData:
    """The current records of every results file or folder, their notes, summaries and tables.

    Raises:
        ResultsError: a line that is not a record (from `read_records`).
    """
    notes: list[str] = []
    by_study = _read_by_study(results, notes)
    digests = checkpoint_digests([record for records in by_study.values() for record in records])
    data = ReportData(records={}, notes=notes)
    for study, records in by_study.items():
        kept, set_aside = current_records(records, digests)
        data.records[study] = kept
        data.notes += [f"{study}: {note}" for note in set_aside]
        repeated = len(records) - len({record.key for record in records})
        if repeated:
            data.notes.append(f"{study}: {repeated} records of rollouts recorded more than once left out (an error "
                              "record is superseded by an outcome of the same rollout): each rollout counts once")
    for study in data.studies:
        data.tables[study], data.summaries[study] = _table(data.records[study])
    return data


def _table(records: list[RolloutRecord]) -> tuple[list[str], dict[tuple[str, str], GroupSummary]]:
    groups: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    for record in records:
        groups[(model_label(record), record.environment)].append(record)
    summaries = {key: summarize(group) for key, group in sorted(groups.items())}
    lines = [("| model | environment | success | rate | 95 % Wilson | of which around the ditch | "
              "failures (status@region) | errors |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (model, env), s in summaries.items():
        failures = ", ".join(f"{k} {v}" for k, v in sorted(s.failure_regions.items())) or "-"
        lines.append(f"| {model} | {env} | {s.successes}/{s.trials} | {_pct(s.rate)} | "
                     f"{_pct(s.low)}-{_pct(s.high)} | {s.around} | {failures} | {s.errors} |")
    return lines, summaries


def _runs_section(results: list[str | os.PathLike]) -> list[str]:
    """A table of the `ditch-drake experiment` runs recorded in the results folders (see
    `runs.record_run`): each stage's wall time; empty if none is recorded."""
    from ditch_drake.evaluation.runs import RUNS_FILE, read_runs

    runs = [run for entry in map(Path, results) if entry.is_dir() for run in read_runs(entry)]
    if not runs:
        return []
    stages = ("collect", "train", "evaluate", "report")
    lines = ["## Wall time", "",
             (f"Each stage's wall time (s) in the `ditch-drake experiment` runs that made these results "
              f"(`{RUNS_FILE}` in the results folder; a stage that found its work done takes seconds; "
              "'-': not run, or still running when this page was written)."), "",
             "| started (UTC) | command | code | CPU | " + " | ".join(f"{stage}_s" for stage in stages)
             + " | total_s |",
             "| --- | --- | --- | --- | " + " | ".join("---:" for _ in stages) + " | ---: |"]
    for run in sorted(runs, key=lambda run: str(run.get("started_utc", ""))):
        times = [run.get(f"{stage}_s") for stage in stages]
        cells = ["-" if t is None else f"{float(t):.0f}" for t in times]
        total = sum(float(t) for t in times if t is not None)
        lines.append(f"| {run.get('started_utc', '?')} | `{run.get('command', '') or '?'}` | {run.get('code', '?')} | "
                     f"{run.get('cpu', '?')} | " + " | ".join(cells) + f" | {total:.0f} |")
    return [*lines, ""]


def _models_table(records: list[RolloutRecord]) -> list[str]:
    """Where each evaluated checkpoint came from, read from the file when it is still there
    (and still the file the rollouts used: same hash prefix)."""
    from ditch_drake.learning.checkpoint import (
        CheckpointError,
        checkpoint_digest,
        load_checkpoint,
        resolve_checkpoint_path,
    )

    lines = ["| model | checkpoint | sha256 | demonstrations (train/val) | epochs (best) | device | training_s |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    used = sorted({(model_label(r), r.checkpoint, r.checkpoint_sha256) for r in records if r.checkpoint})
    for label, path, digest in used:
        row = ["(file gone or changed since)"] + [""] * 3
        try:
            if checkpoint_digest(path) == digest:
                summary = load_checkpoint(resolve_checkpoint_path(path)).summary()
                row = [summary["demos_train/val"], f"{summary['epochs']} ({summary['best_epoch']})",
                       summary["device"], summary["training_s"]]
        except (CheckpointError, OSError):
            pass
        lines.append(f"| {label} | {path} | {digest} | " + " | ".join(row) + " |")
    return lines if used else []


def _pct(value: float) -> str:
    return "n/a" if math.isnan(value) else f"{100 * value:.0f}%"


@dataclass
class _Figure:
    path: Path
    caption: str


def _counted(summary: GroupSummary | None) -> GroupSummary | None:
    """The summary if it has trials to draw, else None (a missing bar)."""
    return summary if summary is not None and summary.trials else None


def _error_bars(summaries: list[GroupSummary | None]) -> list[list[float]]:
    """Matplotlib's yerr for the Wilson intervals (rounding can put a bound a hair past the rate)."""
    return [[max(0.0, s.rate - s.low) if s else 0.0 for s in summaries],
            [max(0.0, s.high - s.rate) if s else 0.0 for s in summaries]]


def _success_axis(ax, ylabel: str = "success rate") -> None:
    ax.set_ylim(0, 1.17)  # Room above a full bar's error bar for its n.
    ax.set_yticks([0, 0.25, 0.5, 0.75, 1.0])
    ax.set_ylabel(ylabel)


def _bars(ax, xs: list[float], summaries: list[GroupSummary | None], width: float = 0.8, label: str | None = None,
          **style) -> None:
    """Bars of the success rates with Wilson error bars, n written above each, and the
    successes that went around the ditch hatched over the bar's bottom."""
    summaries = [_counted(s) for s in summaries]
    ax.bar(xs, [s.rate if s else 0.0 for s in summaries], width, yerr=_error_bars(summaries), capsize=3, label=label,
           **style)
    around = [s.around / s.trials if s else 0.0 for s in summaries]
    if any(around):
        labelled = _AROUND_LABEL in ax.get_legend_handles_labels()[1]
        ax.bar(xs, around, width, label=None if labelled else _AROUND_LABEL, **_AROUND)
    for x, s in zip(xs, summaries):
        ax.text(x, (s.high if s else 0.0) + 0.02, f"n={s.trials}" if s else "none", ha="center", va="bottom",
                fontsize=7)


def _legend_below(fig, ax) -> None:
    """The legend under the axes, outside them, so that it covers no bar."""
    handles, labels = ax.get_legend_handles_labels()
    rows = 0
    if handles:
        # As many columns as fit the figure's width (about 13 characters of 8 pt text an inch).
        room = 13 * fig.get_figwidth()
        columns = next(n for n in range(len(labels), 0, -1)
                       if n == 1 or n * (max(map(len, labels)) + 6) <= room)
        rows = -(-len(labels) // columns)
        fig.legend(handles, labels, loc="lower center", ncol=columns, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.02 + 0.065 * rows * 3.8 / fig.get_figheight(), 1, 1))


def _counts(named: list[tuple[str, GroupSummary | None]]) -> str:
    """'n = 10 rollouts each' or 'n = wide_10: 8, wide_20: 10': the trials behind each point."""
    counts = [(name, s.trials) for name, s in named if _counted(s)]
    if not counts:
        return "no trials"
    if len({n for _, n in counts}) == 1:
        return f"n = {counts[0][1]} rollouts each"
    return "n = " + ", ".join(f"{name}: {n}" for name, n in counts)


def _around_sentence(named: list[tuple[str, GroupSummary | None]]) -> str:
    """Which successes went around the ditch (hatched in the figure), computed from the records."""
    around = [(name, s) for name, s in named if s is not None and s.around]
    if not around:
        return ""
    parts = "; ".join(f"{name}: {s.around} of its {s.successes} successes" for name, s in around)
    return (f" Hatched: successes that went around the ditch's end, never entering it (peak tilt below "
            f"{AROUND_TILT_DEG:g} deg): {parts}.")


def _own_model(scalability: dict, env: str) -> str | None:
    """The model of `env` trained on the most demonstrations in the scalability study."""
    models = [(model_demos(m), m) for (m, e) in scalability if e == env and model_demos(m)
              and model_environments(m) == [env]]
    return max(models)[1] if models else None


def _figure_environment(env: str, scalability: dict, generalization: dict, path: Path, number: int) -> _Figure:
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.8))
    points = sorted((model_demos(m), m, s) for (m, e), s in scalability.items()
                    if e == env and model_demos(m) and _counted(s))
    if points:
        demos = [n for n, _, _ in points]
        left.errorbar(demos, [s.rate for _, _, s in points], yerr=_error_bars([s for _, _, s in points]),
                      marker="o", capsize=3, color=_OWN_MODEL["color"])
        for n, _, s in points:
            left.annotate(f"n={s.trials}", (n, s.high), textcoords="offset points", xytext=(0, 4), ha="center",
                          fontsize=7)
        left.set_xticks(demos)
    left.set(title=f"{env}: scalability", xlabel="demonstrations")
    _success_axis(left)
    own = _own_model(scalability, env)
    bars = [(own, scalability[(own, env)], _OWN_MODEL)] if own else []
    bars += [(m, s, _AMALGAM if "+" in m else _OTHER_MODELS) for (m, e), s in sorted(generalization.items())
             if e == env and m != own]
    for i, (model, summary, style) in enumerate(bars):
        label = ("own environment's model" if style is _OWN_MODEL else
                 "amalgam model" if style is _AMALGAM else "other environments' models")
        labelled = label in right.get_legend_handles_labels()[1]
        _bars(right, [i], [summary], label=None if labelled else label, **style)
    right.set_xticks(range(len(bars)), [m for m, _, _ in bars], rotation=25, ha="right", fontsize=8)
    right.set(title=f"{env}: models from each environment")
    _success_axis(right)
    _legend_below(fig, right)
    _save(fig, path)
    named = [(m, s) for _, m, s in points]
    caption = (f"Figure {number}: {env}. Left: success rate of the {env} models against the number of "
               f"demonstrations ({_counts(named)}). Right: models evaluated in {env}: "
               + (f"its own {own} (blue) and " if own else "")
               + f"the other environments' models (grey) ({_counts([(m, s) for m, s, _ in bars])}; n above "
               f"each bar). {_CI_TEXT}." + _around_sentence(named + [(m, s) for m, s, _ in bars]))
    return _Figure(path, caption)


def _figure_baseline(scalability: dict, baseline: dict, path: Path, number: int) -> _Figure:
    envs = sorted({e for (_, e) in baseline})
    fig, ax = plt.subplots(figsize=(7, 3.8))
    width = 0.38
    owns = {env: _own_model(scalability, env) for env in envs}
    learned = [scalability.get((owns[env], env)) if owns[env] else None for env in envs]
    dwa = [baseline.get(("dwa", env)) for env in envs]
    _bars(ax, [i - width / 2 for i in range(len(envs))], learned, width, label="learned (own environment's model)",
          **_OWN_MODEL)
    _bars(ax, [i + width / 2 for i in range(len(envs))], dwa, width, label="DWA baseline (move_base)", **_BASELINE)
    ax.set_xticks(range(len(envs)), envs)
    ax.set_title("learned policy vs DWA baseline")
    _success_axis(ax)
    _legend_below(fig, ax)
    _save(fig, path)
    models = ", ".join(f"{owns[env]}" for env in envs if owns[env]) or "none evaluated"
    named = [(f"{m} in {env}", s) for env, m, s in zip(envs, [owns[e] for e in envs], learned) if m]
    named += [(f"DWA in {env}", s) for env, s in zip(envs, dwa)]
    caption = (f"Figure {number}: per environment, the learned policy (blue: the environment's own model with the "
               f"most demonstrations: {models}) against the DWA baseline (red) ({_counts(named)}; n above each "
               f"bar; 'none': not evaluated). {_CI_TEXT}." + _around_sentence(named))
    return _Figure(path, caption)


def _figure_amalgam(env: str, amalgam: dict, singles: dict, path: Path, number: int) -> _Figure:
    mixes = [(m, s) for (m, e), s in sorted(amalgam.items()) if e == env]
    demos = {model_demos(m) for m, _ in mixes}
    others = [(m, s) for (m, e), s in sorted(singles.items())
              if e == env and len(model_environments(m)) == 1 and model_demos(m) in demos]
    fig, ax = plt.subplots(figsize=(7, 3.8))
    _bars(ax, list(range(len(mixes))), [s for _, s in mixes], label="amalgam model (trained on several environments)",
          **_AMALGAM)
    _bars(ax, list(range(len(mixes), len(mixes) + len(others))), [s for _, s in others],
          label="single-environment models", **_OTHER_MODELS)
    ax.set_xticks(range(len(mixes) + len(others)), [m for m, _ in mixes + others], rotation=25, ha="right",
                  fontsize=8)
    ax.set_title(f"amalgam vs single-environment models in {env}")
    _success_axis(ax)
    _legend_below(fig, ax)
    _save(fig, path)
    named = mixes + others
    caption = (f"Figure {number}: in {env}, the amalgam model (orange, cross-hatched) against the single-environment "
               f"models with as many demonstrations (grey) ({_counts(named)}; n above each bar). {_CI_TEXT}."
               + _around_sentence(named))
    return _Figure(path, caption)


def _figure_study(study: str, summaries: dict, path: Path, number: int) -> _Figure:
    """Any other results file: success rate per model (bars) and environment (groups)."""
    envs = sorted({e for (_, e) in summaries})
    models = sorted({m for (m, _) in summaries})
    width = 0.8 / len(models)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 + 0.5 * len(envs) * len(models)), 3.8))
    colours = plt.get_cmap("tab10")
    for j, model in enumerate(models):
        style = _AMALGAM if "+" in model else {"color": colours(j % 10)}
        _bars(ax, [i + (j - (len(models) - 1) / 2) * width for i in range(len(envs))],
              [summaries.get((model, env)) for env in envs], width, label=model, **style)
    ax.set_xticks(range(len(envs)), envs)
    ax.set_title(f"{study}: success per model and environment")
    _success_axis(ax)
    _legend_below(fig, ax)
    _save(fig, path)
    named = [(f"{m} in {e}", s) for (m, e), s in sorted(summaries.items())]
    caption = (f"Figure {number}: {study}: success rate of each model (bars) in each environment (groups) "
               f"({_counts(named)}; n above each bar, 'none': not evaluated there). {_CI_TEXT}."
               + _around_sentence(named))
    return _Figure(path, caption)


def _save(fig, path: Path) -> None:
    with atomic_output(path) as file:
        fig.savefig(file, format="png", dpi=110)
    plt.close(fig)


def _figures(data: ReportData, figures_dir: Path) -> tuple[list[_Figure], list[str]]:
    """Every figure the data allows, and a sentence for each results file that gets none."""
    summaries = data.summaries
    scalability, generalization = summaries.get("scalability", {}), summaries.get("generalization", {})
    baseline, amalgam = summaries.get("baseline", {}), summaries.get("amalgam", {})
    figures, missing = [], []
    for env in sorted({e for (_, e) in scalability} | {e for (_, e) in generalization}):
        figures.append(_figure_environment(env, scalability, generalization, figures_dir / f"fig5_{env}.png",
                                           len(figures) + 1))
    if baseline:
        figures.append(_figure_baseline(scalability, baseline, figures_dir / "fig5_baseline.png", len(figures) + 1))
    amalgam_envs = sorted({e for (_, e) in amalgam})
    for env in amalgam_envs:
        name = "fig5_amalgam.png" if len(amalgam_envs) == 1 else f"fig5_amalgam_{env}.png"
        figures.append(_figure_amalgam(env, amalgam, {**generalization, **scalability}, figures_dir / name,
                                       len(figures) + 1))
    for study in data.studies:
        if study in STUDIES:
            continue
        if not any(s.trials for s in summaries[study].values()):
            missing.append(f"No figure for {study}: it holds no trials "
                           f"({len(data.records[study])} current records, all errors or none).")
            continue
        name = re.sub(r"[^A-Za-z0-9_.+-]", "_", study)
        figures.append(_figure_study(study, summaries[study], figures_dir / f"fig_{name}.png", len(figures) + 1))
    return figures, missing


def _findings(scalability: dict, generalization: dict, baseline: dict, amalgam: dict) -> list[str]:
    """The paper's findings (SPEC) beside ours; each verdict computed from the numbers."""
    rows = ["| paper's finding | ours | agree? |", "| --- | --- | --- |"]

    def rate(summaries, model, env):
        s = summaries.get((model, env))
        return None if s is None or s.trials == 0 else s.rate

    envs = sorted({e for (_, e) in scalability} | {e for (_, e) in baseline})
    rising = []
    for env in envs:
        series = sorted((model_demos(m), s.rate) for (m, e), s in scalability.items() if e == env and model_demos(m))
        if len(series) >= 2:
            rising.append((env, series[-1][1] >= series[0][1], series))
    if rising:
        ours = "; ".join(f"{env} " + " -> ".join(f"{n}: {_pct(r)}" for n, r in series) for env, _, series in rising)
        rows.append(f"| success generally rises with demonstrations | {ours} | "
                    f"{'yes' if sum(up for _, up, _ in rising) * 2 > len(rising) else 'no'} |")
    beats = []
    for env in envs:
        learned, dwa = rate(scalability, f"{env}_40", env), rate(baseline, "dwa", env)
        if learned is not None and dwa is not None:
            beats.append((env, learned, dwa))
    if beats:
        ours = "; ".join(f"{env} {_pct(a)} vs {_pct(b)}" for env, a, b in beats)
        around = sum(baseline[("dwa", env)].around for env, _, _ in beats)
        if around:
            successes = sum(baseline[("dwa", env)].successes for env, _, _ in beats)
            ours += (f" (but {around} of the baseline's {successes} successes went around the ditch, never "
                     "entering it: the environments let it bypass the obstacle)")
        rows.append(f"| every learned model beats move_base in its own environment | {ours} | "
                    f"{'yes' if all(a > b for _, a, b in beats) else 'no'} |")
    if generalization:
        mean_by_model = defaultdict(list)
        for (model, _), s in generalization.items():
            if s.trials:
                mean_by_model[model].append(s.rate)
        means = {m: sum(v) / len(v) for m, v in mean_by_model.items()}
        if means:
            best, worst = max(means, key=means.get), min(means, key=means.get)
            ours = ", ".join(f"{m} {_pct(v)}" for m, v in sorted(means.items()))
            agree = best.startswith("crater") and worst.startswith("sine")
            rows.append(f"| the Crater model generalizes best, the Sine model worst | mean over other environments: "
                        f"{ours} | {'yes' if agree else 'no'} |")
    for (model, env), s in amalgam.items():
        singles = [g.rate for (m, e), g in generalization.items() if e == env and g.trials]
        if singles and s.trials:
            average = sum(singles) / len(singles)
            rows.append(f"| the amalgam beats the average of the single models in {env} | {model} {_pct(s.rate)} vs "
                        f"average {_pct(average)} | {'yes' if s.rate > average else 'no'} |")
    return rows


def write_report(results: list[str | os.PathLike], out: str | os.PathLike, figures_dir: str | os.PathLike,
                 title: str = "Results", command: str = "", data: ReportData | None = None) -> Path:
    """Writes the results page and its figures (atomically); returns the page's path.

    Args:
        results: results files or folders of them.
        out: the Markdown page.
        figures_dir: the folder of its PNG figures.
        title: the page's title.
        command: the command that made the page, written on it.
        data: `load_report_data(results)` if already loaded.

    Raises:
        ResultsError: a line that is not a record (from `read_records`).
    """
    out, figures_dir = Path(out), Path(figures_dir)
    for folder in (out.parent, figures_dir):
        remove_stale_temporaries(folder)
    data = data if data is not None else load_report_data(results)
    lines = [f"# {title}", ""]
    if command:
        lines += ["Made by", "", f"    {command}", ""]
    lines += _runs_section(results)
    if data.notes:
        lines += ["## Records not counted", "",
                  ("Each rollout counts once, by its latest real outcome, and each checkpoint name by one version "
                   "of its file (the file as it is now, where it still resolves):"), "",
                  *(f"- {note}" for note in data.notes), ""]
    for study in data.studies:
        lines += [f"## {study}", "", *data.tables[study], ""]
    figures, missing = _figures(data, figures_dir)
    models = _models_table([record for records in data.records.values() for record in records])
    if models:
        lines += ["## Models", "", "What each evaluated checkpoint was trained on, and where (read from the file).", "",
                  *models, ""]
    if figures or missing:
        lines += ["## Figures", ""]
        for figure in figures:
            lines += [f"![{figure.path.stem}]({os.path.relpath(figure.path, out.parent)})", "", f"*{figure.caption}*",
                      ""]
        lines += [*(f"*{sentence}*" for sentence in missing), ""] if missing else []
    if any(study in data.records for study in STUDIES):
        summaries = data.summaries
        lines += ["## The paper's findings and ours", "",
                  *_findings(summaries.get("scalability", {}), summaries.get("generalization", {}),
                             summaries.get("baseline", {}), summaries.get("amalgam", {})), ""]
    return atomic_write_text(out, "\n".join(lines))
