"""The results page: success rates with Wilson intervals, failures, Figure 5-style plots.

`write_report(results, out_md, figures_dir)` reads every results file (JSON Lines from
`evaluate` / `experiment`), groups the rollouts by study, and writes a Markdown page with

- one table per study: model, environment, successes / trials, rate and 95 % Wilson
  interval, failures by status and region;
- figures in the style of the paper's Figure 5 (PNG, matplotlib): (a-d) per environment,
  success against the number of demonstrations (scalability) beside the other
  environments' models in it (generalization); (e) the learned policy against the DWA
  baseline per environment; (f) the amalgam model against the single-environment models
  in the amalgam's evaluation environment;
- the paper's stated findings (SPEC "Experiments") beside ours, each marked as agreeing or
  not by a rule computed from the numbers, never by hand.

A study is recognized from a results file's name (`scalability.jsonl`, ...); any other
file gets a table of its own, under its name, and no figure. The findings table is
written when at least one of the paper's studies is present.
"""

import math
import os
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from ditch_drake.evaluation.results import RolloutRecord, read_records
from ditch_drake.evaluation.summary import GroupSummary, summarize

STUDIES = ("scalability", "generalization", "baseline", "amalgam")


def model_label(record: RolloutRecord) -> str:
    """A short name of the controller: the checkpoint's file stem, or the controller."""
    return Path(record.checkpoint).stem if record.checkpoint else record.controller


def model_demos(label: str) -> int | None:
    """N of a model named `<envs>_<N>` (as the experiment names them), else None."""
    tail = label.rsplit("_", 1)[-1]
    return int(tail) if tail.isdigit() else None


def model_environments(label: str) -> list[str]:
    return label.rsplit("_", 1)[0].split("+") if model_demos(label) is not None else [label]


def load_by_study(results: list[str | os.PathLike]) -> dict[str, list[RolloutRecord]]:
    """Records per results file name (a study's, or any other), from files or folders of them."""
    by_study: dict[str, list[RolloutRecord]] = defaultdict(list)
    for entry in results:
        entry = Path(entry)
        for file in sorted(entry.glob("*.jsonl")) if entry.is_dir() else [entry]:
            by_study[file.stem] += read_records(file)[0]
    return dict(by_study)


def _table(records: list[RolloutRecord]) -> tuple[list[str], dict[tuple[str, str], GroupSummary]]:
    groups: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    for record in records:
        groups[(model_label(record), record.environment)].append(record)
    summaries = {key: summarize(group) for key, group in sorted(groups.items())}
    lines = ["| model | environment | success | rate | 95 % Wilson | of which around the ditch | "
             "failures (status@region) | errors |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (model, env), s in summaries.items():
        failures = ", ".join(f"{k} {v}" for k, v in sorted(s.failure_regions.items())) or "-"
        lines.append(f"| {model} | {env} | {s.successes}/{s.trials} | {_pct(s.rate)} | "
                     f"{_pct(s.low)}-{_pct(s.high)} | {s.around} | {failures} | {s.errors} |")
    return lines, summaries


def _runs_section(results: list[str | os.PathLike]) -> list[str]:
    """A table of the `ditch-drake experiment` runs recorded in the results folders (see
    `experiment.record_run`): each stage's wall time; empty if none is recorded."""
    from ditch_drake.evaluation.experiment import RUNS_FILE, read_runs

    runs = [run for entry in map(Path, results) if entry.is_dir() for run in read_runs(entry)]
    if not runs:
        return []
    stages = ("collect", "train", "evaluate", "report")
    lines = ["## Wall time", "",
             (f"Each stage's wall time (s) in the `ditch-drake experiment` runs that made these results "
              f"(`{RUNS_FILE}` in the results folder; a stage that found its work done takes seconds; "
              "'-': not run, or still running when this page was written)."), "",
             "| started (UTC) | command | code | CPU | " + " | ".join(f"{stage}_s" for stage in stages) + " | total_s |",
             "| --- | --- | --- | --- | " + " | ".join("---:" for _ in stages) + " | ---: |"]
    for run in sorted(runs, key=lambda run: str(run.get("started_utc", ""))):
        times = [run.get(f"{stage}_s") for stage in stages]
        cells = ["-" if t is None else f"{float(t):.0f}" for t in times]
        total = sum(float(t) for t in times if t is not None)
        lines.append(f"| {run.get('started_utc', '?')} | `{run.get('command', '') or '?'}` | {run.get('code', '?')} | {run.get('cpu', '?')} | "
                     + " | ".join(cells) + f" | {total:.0f} |")
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


def _error_bars(summaries) -> list[list[float]]:
    """Matplotlib's yerr for the Wilson intervals (rounding can put a bound a hair past the rate)."""
    return [[max(0.0, s.rate - s.low) if s else 0.0 for s in summaries],
            [max(0.0, s.high - s.rate) if s else 0.0 for s in summaries]]


def _bars(ax, labels, summaries, colour):
    rates = [s.rate for s in summaries]
    errors = _error_bars(summaries)
    ax.bar(labels, rates, yerr=errors, capsize=3, color=colour)
    ax.set_ylim(0, 1.05)


def _figure_environment(env: str, scalability: dict, generalization: dict, path: Path) -> None:
    fig, (left, right) = plt.subplots(1, 2, figsize=(8, 3.2))
    points = sorted((model_demos(m), s) for (m, e), s in scalability.items() if e == env and model_demos(m))
    if points:
        demos = [n for n, _ in points]
        left.errorbar(demos, [s.rate for _, s in points], yerr=_error_bars([s for _, s in points]),
                      marker="o", capsize=3)
        left.set_xticks(demos)
    left.set(title=f"{env}: scalability", xlabel="demonstrations", ylabel="success rate", ylim=(0, 1.05))
    others = [(m, s) for (m, e), s in generalization.items() if e == env]
    own = [(m, s) for (m, e), s in scalability.items() if e == env and model_demos(m) == 40]
    bars = own + others
    if bars:
        _bars(right, [m for m, _ in bars], [s for _, s in bars], ["tab:blue"] * len(own) + ["tab:gray"] * len(others))
    right.set(title=f"{env}: models from each environment", ylabel="success rate", ylim=(0, 1.05))
    right.tick_params(axis="x", labelrotation=30)
    fig.tight_layout()
    _save(fig, path)


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(temporary, dpi=110)
    plt.close(fig)
    os.replace(temporary, path)


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
                 title: str = "Results", command: str = "") -> Path:
    """Writes the results page and its figures (atomically); returns the page's path."""
    out, figures_dir = Path(out), Path(figures_dir)
    by_study = load_by_study(results)
    lines = [f"# {title}", ""]
    if command:
        lines += ["Made by", "", f"    {command}", ""]
    lines += _runs_section(results)
    summaries: dict[str, dict] = {}
    for study in [*(study for study in STUDIES if study in by_study), *sorted(set(by_study) - set(STUDIES))]:
        table, summaries[study] = _table(by_study[study])
        lines += [f"## {study}", "", *table, ""]
    scalability, generalization = summaries.get("scalability", {}), summaries.get("generalization", {})
    baseline, amalgam = summaries.get("baseline", {}), summaries.get("amalgam", {})
    figures = []
    for env in sorted({e for (_, e) in scalability} | {e for (_, e) in generalization}):
        path = figures_dir / f"fig5_{env}.png"
        _figure_environment(env, scalability, generalization, path)
        figures.append(path)
    envs = sorted({e for (_, e) in baseline})
    if envs:
        fig, ax = plt.subplots(figsize=(6, 3.2))
        width = 0.38
        for offset, (label, summaries_of, model_of) in enumerate(
                (("learned (own 40-demo model)", scalability, lambda e: f"{e}_40"), ("DWA baseline", baseline,
                                                                                      lambda e: "dwa"))):
            values = [summaries_of.get((model_of(e), e)) for e in envs]
            xs = [i + (offset - 0.5) * width for i in range(len(envs))]
            ax.bar(xs, [v.rate if v else 0 for v in values], width, label=label, yerr=_error_bars(values), capsize=3)
        ax.set_xticks(range(len(envs)), envs)
        ax.set(ylim=(0, 1.05), ylabel="success rate", title="learned policy vs DWA baseline")
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = figures_dir / "fig5_baseline.png"
        _save(fig, path)
        figures.append(path)
    if amalgam:
        fig, ax = plt.subplots(figsize=(6, 3.2))
        env = next(iter(amalgam))[1]
        entries = [(m, s) for (m, e), s in amalgam.items()] + [
            (m, s) for (m, e), s in {**generalization, **scalability}.items() if e == env and model_demos(m) == 40]
        _bars(ax, [m for m, _ in entries], [s for _, s in entries], "tab:green")
        ax.set(title=f"amalgam vs single models in {env}", ylabel="success rate")
        ax.tick_params(axis="x", labelrotation=30)
        fig.tight_layout()
        path = figures_dir / "fig5_amalgam.png"
        _save(fig, path)
        figures.append(path)
    models = _models_table([record for records in by_study.values() for record in records])
    if models:
        lines += ["## Models", "", "What each evaluated checkpoint was trained on, and where (read from the file).", "",
                  *models, ""]
    if figures:
        lines += ["## Figures", ""] + [f"![{p.stem}]({os.path.relpath(p, out.parent)})" for p in figures] + [""]
    if any(study in by_study for study in STUDIES):
        lines += ["## The paper's findings and ours", "",
                  *_findings(scalability, generalization, baseline, amalgam), ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    temporary = out.with_name(f".{out.name}.tmp")
    temporary.write_text("\n".join(lines))
    os.replace(temporary, out)
    return out
