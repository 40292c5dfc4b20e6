"""The results page: success rates with Wilson intervals, failures, Figure 5-style plots.

`write_report(results, out_md, figures_dir)` reads every results file (JSON Lines from
`evaluate` / `experiment`), keeps the current records of each (`load_report_data`), groups
them by study, and writes a Markdown page with

- one table per study: model, environment, successes / trials, rate and 95 % Wilson
  interval, failures by status and region;
- figures in the style of the paper's Figure 5 (PNG, matplotlib), each with a caption
  under it: (a-d) per environment, success against the number of demonstrations
  (scalability) beside the other environments' models in it (generalization); (e) the
  learned models against move_base per environment: in the walled environments of the
  must_cross study (every route crosses the ditch: the like-for-like comparison, issue 20)
  each environment's learned models against `dwa_paper` (the paper's move_base) and `dwa`,
  and in the open field the learned policy against the DWA baseline (and `dwa_paper`
  where measured); (f) the amalgam model against the single-environment models in the
  amalgam's evaluation environment; and for any other results file, its success rate per
  model and environment;
- the paper's stated findings (SPEC "Experiments") beside ours, each marked as agreeing or
  not by a rule computed from the numbers, never by hand. "Every learned model beats
  move_base in its own environment" is tested pair by pair (each learned model against the
  classical controller in the same environment) with Boschloo's exact test
  (`two_proportion_test`), on the walled environments and, beside them, in the open field;
  the rule is stated on the page. The must_cross study's classical controllers' halts are
  shown by region, where the records count them.

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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from scipy.stats import boschloo_exact

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import atomic_write_text, remove_stale_temporaries, save_figure
from ditch_drake.evaluation.results import RolloutRecord, current_records, read_records
from ditch_drake.evaluation.summary import AROUND_TILT_DEG, GroupSummary, summarize
from ditch_drake.world.regions import REGIONS

STUDIES = ("scalability", "generalization", "baseline", "amalgam", "must_cross")
# The paper's move_base (slope cost, flat = 0, no slope lethal; issue 20) and our DWA baseline
# (slopes from 45 deg lethal), the classical controllers the learned models are compared with.
PAPER_MOVE_BASE = "dwa_paper"
DWA = "dwa"
_CONTROLLER_NAMES = {PAPER_MOVE_BASE: "the paper's move_base (dwa_paper: slope cost, no slope lethal)",
                     DWA: "our DWA baseline (dwa: slopes from 45 deg lethal)"}
# Significance level of the two-proportion tests behind the findings' verdicts.
ALPHA = 0.05
# What each kind of bar is drawn as (colour, hatch), so the figures agree with each other.
_OWN_MODEL = {"color": "tab:blue"}
_PAPER_MODEL = {"color": "lightskyblue", "edgecolor": "tab:blue"}  # An own model, the paper's method alone.
_OTHER_MODELS = {"color": "tab:gray"}
_BASELINE = {"color": "tab:red"}
_PAPER_BASELINE = {"color": "lightsalmon", "edgecolor": "tab:red"}
_AMALGAM = {"color": "tab:orange", "hatch": "xx", "edgecolor": "black"}
_AROUND = {"fill": False, "hatch": "///", "edgecolor": "black", "linewidth": 0.0}
_AROUND_LABEL = f"successes that went around the ditch (peak tilt < {AROUND_TILT_DEG:g} deg)"
_CI_TEXT = "Error bars: 95 % Wilson score intervals"


def model_label(record: RolloutRecord) -> str:
    """A short name of the controller: the checkpoint's file stem, or the controller."""
    return Path(record.checkpoint).stem if record.checkpoint else record.controller


def controller_labels(records: list[RolloutRecord]) -> Callable[[RolloutRecord], str]:
    """Each record's controller as the page names it: `model_label` (the checkpoint's file
    stem), preceded by its folder where checkpoints of one stem lie in several."""
    paths = defaultdict(set)
    for record in records:
        if record.checkpoint:
            paths[model_label(record)].add(record.checkpoint)
    shared = {stem for stem, found in paths.items() if len(found) > 1}

    def label(record: RolloutRecord) -> str:
        stem = model_label(record)
        folder = Path(record.checkpoint).parent.name if stem in shared else ""
        return f"{folder}/{stem}" if folder else stem

    return label


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
    name_of = controller_labels(records)
    for record in records:
        groups[(name_of(record), record.environment)].append(record)
    summaries = {key: summarize(group) for key, group in sorted(groups.items())}
    lines = [("| model | environment | success | rate | 95 % Wilson | of which around the ditch | "
              "failures (status@region) | halts (region) | errors |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (model, env), s in summaries.items():
        failures = ", ".join(f"{k} {v}" for k, v in sorted(s.failure_regions.items())) or "-"
        # The regions a crossing meets, in order; "-": records from before halts were counted.
        halts = ", ".join(f"{k} {v}" for k, v in s.halts_by_region.items() if v) or ("0" if s.halts_counted else "-")
        if 0 < s.halts_counted < s.trials:
            halts += f" (in {s.halts_counted} of {s.trials} trials)"
        lines.append(f"| {model} | {env} | {s.successes}/{s.trials} | {_pct(s.rate)} | "
                     f"{_pct(s.low)}-{_pct(s.high)} | {s.around} | {failures} | {halts} | {s.errors} |")
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
    name_of = controller_labels(records)
    used = sorted({(name_of(r), r.checkpoint, r.checkpoint_sha256) for r in records if r.checkpoint})
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


def two_proportion_test(successes_a: int, trials_a: int, successes_b: int, trials_b: int) -> float:
    """Two-sided p-value of "both groups succeed at the same rate": Boschloo's exact test
    (`scipy.stats.boschloo_exact`) on the 2x2 table whose columns are the two groups.

    Exact, so it holds at 30 trials a group and at rates of 0 or 1, where a z-test's normal
    approximation does not; unconditional (each group's trials are fixed by the design, the
    total of successes is not), and uniformly more powerful than Fisher's exact test, whose
    p-value it takes as its statistic. A table without evidence either way (both groups all
    successes, or all failures: scipy gives nan) has p = 1, as in Fisher's test.

    Raises:
        ValueError: counts out of range, or a group without trials.
    """
    if not (0 <= successes_a <= trials_a and 0 <= successes_b <= trials_b and trials_a and trials_b):
        raise ValueError(f"successes {successes_a}/{trials_a} and {successes_b}/{trials_b}: need "
                         "0 <= successes <= trials and trials >= 1 in each group")
    table = [[successes_a, successes_b], [trials_a - successes_a, trials_b - successes_b]]
    p_value = float(boschloo_exact(table, alternative="two-sided").pvalue)
    return 1.0 if math.isnan(p_value) else p_value


@dataclass
class Comparison:
    """A learned model against a classical controller in one environment (both with trials)."""

    environment: str
    model: str
    learned: GroupSummary
    controller: str
    baseline: GroupSummary
    p_value: float

    @property
    def beats(self) -> bool:
        """The learned model's rate is higher and the difference significant at `ALPHA`."""
        return self.learned.rate > self.baseline.rate and self.p_value < ALPHA


def compare(environment: str, model: str, learned: GroupSummary | None, controller: str,
            baseline: GroupSummary | None) -> Comparison | None:
    """The comparison of two groups, tested (`two_proportion_test`); None if one has no trials."""
    if not (_counted(learned) and _counted(baseline)):
        return None
    p_value = two_proportion_test(learned.successes, learned.trials, baseline.successes, baseline.trials)
    return Comparison(environment, model, learned, controller, baseline, p_value)


def beats_verdict(comparisons: list[Comparison]) -> str:
    """The verdict on "every learned model beats move_base": "yes" when every learned model's
    rate is higher with p < `ALPHA`; "no" when some learned model's rate is not higher; "not
    significant" when all are higher but some p >= `ALPHA`.

    Requiring every pair to pass at `ALPHA` is an intersection-union test: the claim about all
    of them together is tested at level `ALPHA`, with no correction for their number.
    """
    if not all(c.learned.rate > c.baseline.rate for c in comparisons):
        return "no"
    return "yes" if all(c.beats for c in comparisons) else "not significant"


def _verdict_rule(alpha: float = ALPHA) -> str:
    return (f"Verdict on \"beats move_base\": each learned model is compared with the classical controller in its own "
            f"environment, pair by pair, by a two-sided Boschloo exact test (`scipy.stats.boschloo_exact`; the "
            f"2x2 table of successes and failures of the two groups). 'yes' when every learned model's success "
            f"rate is higher and every pair's p < {alpha:g}; 'no' when some learned model's rate is not higher; "
            f"'not significant' when all are higher but some p >= {alpha:g}. Requiring every pair to pass is an "
            f"intersection-union test, so the claim about all of them is tested at level {alpha:g} without a "
            "correction for their number. Why Boschloo: it is exact (a z-test's normal approximation fails with 30 "
            "rollouts a group and rates at 0 or 1), unconditional (each group's rollouts are fixed by the design, "
            "the total of successes is not, which Fisher's test conditions on), and uniformly more powerful than "
            "Fisher's exact test. Both groups all successes or all failures: p = 1.")


def walled_base(environment: str, environments_file: str = "") -> str:
    """The open environment a walled one is made from (its `Environment.based_on`), "" for an
    open one; for a name that no longer resolves, the `<env>_walled` naming convention."""
    from ditch_drake.world.environments import get_environment

    try:
        return get_environment(environment, environments_file or None).based_on
    except ConfigError:
        return environment.removesuffix("_walled") if environment.endswith("_walled") else ""


@dataclass
class MustCross:
    """The must_cross study's groups (issue 20), sorted for the page.

    Attributes:
        walled: each walled environment evaluated -> the open environment it is made from.
        learned: per walled environment, its learned models' (label, summary): the shipped
            models (no number of demonstrations in the name), then the paper-method ones.
        controllers: per classical controller (`dwa_paper` first, then `dwa`, then any
            other), its summary per environment, walled and open.
        open_learned: per open environment, the learned models the study ran there (on the
            same seeds as in the walled ones), sorted as `learned`.
    """

    walled: dict[str, str]
    learned: dict[str, list[tuple[str, GroupSummary]]]
    controllers: dict[str, dict[str, GroupSummary]]
    open_learned: dict[str, list[tuple[str, GroupSummary]]] = field(default_factory=dict)

    def comparisons(self, controller: str) -> list[Comparison]:
        """Every learned model against `controller` in each walled environment where both ran."""
        found = [compare(env, model, s, controller, self.controllers.get(controller, {}).get(env))
                 for env in self.walled for model, s in self.learned.get(env, [])]
        return [c for c in found if c is not None]

    def open_field(self, controller: str) -> dict[str, GroupSummary]:
        """`controller`'s summaries in the open environments."""
        return {env: s for env, s in self.controllers.get(controller, {}).items() if env not in self.walled}


def must_cross_groups(data: ReportData) -> MustCross | None:
    """The must_cross study's groups (None without its results): a group is a learned model's
    when its records name a checkpoint, else a classical controller's."""
    records = data.records.get("must_cross")
    if not records:
        return None
    files = {record.environment: record.environments_file for record in records}
    walled = {env: base for env in sorted(files) if (base := walled_base(env, files[env]))}
    name_of = controller_labels(records)  # As `_table` named the study's groups.
    learned_labels = {name_of(record) for record in records if record.checkpoint}
    learned: dict[str, list[tuple[str, GroupSummary]]] = defaultdict(list)
    open_learned: dict[str, list[tuple[str, GroupSummary]]] = defaultdict(list)
    controllers: dict[str, dict[str, GroupSummary]] = defaultdict(dict)
    for (label, env), summary in data.summaries["must_cross"].items():
        if label not in learned_labels:
            controllers[label][env] = summary
        else:
            (learned if env in walled else open_learned)[env].append((label, summary))
    for models in (*learned.values(), *open_learned.values()):
        models.sort(key=lambda item: (model_demos(item[0]) is not None, item[0]))
    order = sorted(controllers, key=lambda name: (name != PAPER_MOVE_BASE, name != DWA, name))
    return MustCross(walled, dict(learned), {name: controllers[name] for name in order}, dict(open_learned))


def _comparisons_cell(comparisons: list[Comparison]) -> str:
    """'wide_walled: wide 90% (p=1e-05), wide_40 70% (p=0.003) vs 10%; ...; 2 of 2 pairs higher with p < 0.05'."""
    by_env: dict[str, list[Comparison]] = defaultdict(list)
    for c in comparisons:
        by_env[c.environment].append(c)
    parts = [f"{env}: " + ", ".join(f"{c.model} {_pct(c.learned.rate)} (p={_p(c.p_value)})" for c in group)
             + f" vs {_pct(group[0].baseline.rate)}" for env, group in by_env.items()]
    passed = sum(c.beats for c in comparisons)
    return "; ".join(parts) + f"; {passed} of {len(comparisons)} pairs higher with p < {ALPHA:g}"


def _p(value: float) -> str:
    return f"{value:.2g}"


def _comparisons_table(named: list[tuple[str, list[Comparison]]]) -> list[str]:
    """Every pair behind the verdicts: (setting, its comparisons)."""
    lines = [("| setting | environment | learned model | success | 95 % Wilson | against | success | 95 % Wilson | "
             "p (Boschloo, two-sided) | higher, p < 0.05 |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for setting, comparisons in named:
        for c in comparisons:
            lines.append(f"| {setting} | {c.environment} | {c.model} | {c.learned.successes}/{c.learned.trials} | "
                         f"{_pct(c.learned.low)}-{_pct(c.learned.high)} | {c.controller} | "
                         f"{c.baseline.successes}/{c.baseline.trials} | {_pct(c.baseline.low)}-{_pct(c.baseline.high)} | "
                         f"{_p(c.p_value)} | {'yes' if c.beats else 'no'} |")
    return lines if len(lines) > 2 else []


def _halts(summary: GroupSummary) -> dict[str, int]:
    """A group's halts per region (`GroupSummary.halts_by_region`; empty where its records do
    not count them, or before the summaries had the field)."""
    return dict(getattr(summary, "halts_by_region", None) or {})


def _halts_table(must_cross: MustCross) -> list[str]:
    """The classical controllers' halts by region, walled environments first; empty when no
    group's records count halts ('-': this group's do not)."""
    rows = [(name, env, s) for name, by_env in must_cross.controllers.items()
            for env, s in sorted(by_env.items(), key=lambda item: (item[0] not in must_cross.walled, item[0]))]
    if not any(_halts(s) for _, _, s in rows):
        return []
    lines = ["| controller | environment | rollouts | " + " | ".join(REGIONS) + " | total |",
             "| --- | --- | ---: | " + " | ".join("---:" for _ in REGIONS) + " | ---: |"]
    for name, env, s in rows:
        counts = _halts(s)
        cells = [str(counts.get(region, 0)) if counts else "-" for region in REGIONS]
        lines.append(f"| {name} | {env} | {s.trials} | " + " | ".join(cells)
                     + f" | {sum(counts.values()) if counts else '-'} |")
    return lines


def _backslope_row(must_cross: MustCross) -> list[str]:
    """The paper's move_base mostly failed on the backslope after halting to replan (paper 5):
    where its failures in the walled environments ended, and where it halted."""
    groups = [s for env, s in must_cross.controllers.get(PAPER_MOVE_BASE, {}).items()
              if env in must_cross.walled and _counted(s)]
    if not groups:
        return []
    failures = sum(s.trials - s.successes for s in groups)
    up = sum(n for s in groups for key, n in s.failure_regions.items() if key.endswith("@up_wall"))
    ours = f"{PAPER_MOVE_BASE} in the walled environments: {up} of its {failures} failures ended on the up wall"
    recorded = [_halts(s) for s in groups]
    halted = True
    if all(recorded):
        up_halts, halts = sum(h.get("up_wall", 0) for h in recorded), sum(sum(h.values()) for h in recorded)
        ours += f"; {up_halts} of its {halts} halts were on the up wall"
        halted = up_halts > 0
    else:
        ours += "; halts not recorded"
    agree = failures > 0 and 2 * up > failures and halted
    return [(f"| move_base mostly failed on the backslope, after halting to replan (walled) | {ours} | "
            f"{'yes' if agree else 'no'} |")]


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
    save_figure(fig, path, dpi=110)
    named = [(m, s) for _, m, s in points]
    caption = (f"Figure {number}: {env}. Left: success rate of the {env} models against the number of "
               f"demonstrations ({_counts(named)}). Right: models evaluated in {env}: "
               + (f"its own {own} (blue) and " if own else "")
               + f"the other environments' models (grey) ({_counts([(m, s) for m, s, _ in bars])}; n above "
               f"each bar). {_CI_TEXT}." + _around_sentence(named + [(m, s) for m, s, _ in bars]))
    return _Figure(path, caption)


def _figure_baseline(scalability: dict, baseline: dict, path: Path, number: int,
                     paper: dict[str, GroupSummary] | None = None,
                     shipped: dict[str, tuple[str, GroupSummary]] | None = None) -> _Figure:
    """The open field: each environment's own model against the DWA baseline, and against the
    paper's move_base (`paper`: its summary per open environment, from must_cross) where measured;
    `shipped`: per open environment, the shipped model's (label, summary) that must_cross ran there."""
    paper, shipped = paper or {}, shipped or {}
    envs = sorted({e for (_, e) in baseline} | set(paper))
    fig, ax = plt.subplots(figsize=(7, 3.8))
    owns = {env: _own_model(scalability, env) for env in envs}
    learned = [scalability.get((owns[env], env)) if owns[env] else None for env in envs]
    dwa = [baseline.get((DWA, env)) for env in envs]
    series = []
    if any(env in shipped for env in envs):
        series.append(([shipped[env][1] if env in shipped else None for env in envs],
                       "learned: the environment's shipped model", _OWN_MODEL))
    if any(learned) or not series:
        label = "learned: the paper's method, own environment's model" if series else "learned (own environment's model)"
        series.append((learned, label, _PAPER_MODEL if series else _OWN_MODEL))
    series += [(dwa, "DWA baseline (dwa)", _BASELINE)] if baseline else []
    series += [([paper.get(env) for env in envs], "the paper's move_base (dwa_paper)", _PAPER_BASELINE)] if paper else []
    width = 0.8 / len(series)
    for j, (summaries, label, style) in enumerate(series):
        _bars(ax, [i + (j - (len(series) - 1) / 2) * width for i in range(len(envs))], summaries, width, label=label,
              **style)
    ax.set_xticks(range(len(envs)), envs)
    ax.set_title("open field (the ditch can be bypassed): learned policy vs move_base")
    _success_axis(ax)
    _legend_below(fig, ax)
    save_figure(fig, path, dpi=110)
    models = ", ".join(f"{owns[env]}" for env in envs if owns[env]) or "none evaluated"
    named = [(f"{shipped[env][0]} in {env}", shipped[env][1]) for env in envs if env in shipped]
    named += [(f"{m} in {env}", s) for env, m, s in zip(envs, [owns[e] for e in envs], learned) if m]
    named += [(f"DWA in {env}", s) for env, s in zip(envs, dwa)] if baseline else []
    named += [(f"dwa_paper in {env}", paper.get(env)) for env in envs] if paper else []
    against = " and ".join([*(["the DWA baseline (red)"] if baseline else []),
                            *(["the paper's move_base, dwa_paper (light red)"] if paper else [])])
    learners = (["the environment's shipped model (blue; the must_cross study's runs)"] if shipped else [])
    own = f"the environment's own model with the most demonstrations ({'light blue' if shipped else 'blue'}: {models})"
    learners += [own] if any(learned) or not shipped else []
    caption = (f"Figure {number}: in the open field, per environment, {' and '.join(learners)} against {against} "
               f"({_counts(named)}; n above each "
               f"bar; 'none': not evaluated). {_CI_TEXT}." + _around_sentence(named))
    return _Figure(path, caption)


def _figure_must_cross(must_cross: MustCross, path: Path, number: int) -> _Figure:
    """The paper's Figure 5e like for like: per walled environment, its learned models against
    the classical controllers."""
    envs = list(must_cross.walled)

    def model(env: str, shipped: bool) -> tuple[str, GroupSummary] | tuple[None, None]:
        models = [(m, s) for m, s in must_cross.learned.get(env, []) if (model_demos(m) is None) == shipped]
        return max(models, key=lambda item: model_demos(item[0]) or 0) if models else (None, None)

    shipped, paper = [model(env, True) for env in envs], [model(env, False) for env in envs]
    demos = sorted({model_demos(m) for m, _ in paper if m})
    colours = plt.get_cmap("tab10")
    series = [(shipped, "learned: shipped model of the base environment", _OWN_MODEL),
              (paper, "learned: the paper's method" + (f", {', '.join(map(str, demos))} demonstrations" if demos else ""),
               _PAPER_MODEL)]
    styles = {PAPER_MOVE_BASE: _PAPER_BASELINE, DWA: _BASELINE}
    series += [([(name, by_env.get(env)) for env in envs], _CONTROLLER_NAMES.get(name, name),
                styles.get(name, {"color": colours((4 + j) % 10)}))
               for j, (name, by_env) in enumerate(must_cross.controllers.items())]
    series = [item for item in series if any(_counted(s) for _, s in item[0])]
    width = 0.8 / max(1, len(series))
    fig, ax = plt.subplots(figsize=(max(7.0, 1.2 + 0.45 * len(envs) * len(series)), 3.8))
    for j, (bars, label, style) in enumerate(series):
        _bars(ax, [i + (j - (len(series) - 1) / 2) * width for i in range(len(envs))], [s for _, s in bars], width,
              label=label, **style)
    ax.set_xticks(range(len(envs)), envs)
    ax.set_title("walled (every route crosses the ditch): learned models vs move_base")
    _success_axis(ax)
    _legend_below(fig, ax)
    save_figure(fig, path, dpi=110)
    named = [(f"{m} in {env}", s) for bars, _, _ in series for (m, s), env in zip(bars, envs) if m]
    caption = (f"Figure {number}: the paper's Figure 5e like for like: per walled environment (the ditch and tasks "
               "of its base environment, fenced so that every route crosses the ditch), the learned models "
               "(blue: the base environment's shipped model; light blue: the paper's method alone, the experiment's "
               "own model) against the paper's move_base (dwa_paper, light red) and our DWA (dwa, red: slopes from "
               f"45 deg lethal) ({_counts(named)}; n above each bar; 'none': not evaluated). {_CI_TEXT}."
               + _around_sentence(named))
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
    save_figure(fig, path, dpi=110)
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
    save_figure(fig, path, dpi=110)
    named = [(f"{m} in {e}", s) for (m, e), s in sorted(summaries.items())]
    caption = (f"Figure {number}: {study}: success rate of each model (bars) in each environment (groups) "
               f"({_counts(named)}; n above each bar, 'none': not evaluated there). {_CI_TEXT}."
               + _around_sentence(named))
    return _Figure(path, caption)


def _figures(data: ReportData, figures_dir: Path,
             must_cross: MustCross | None = None) -> tuple[list[_Figure], list[str]]:
    """Every figure the data allows, and a sentence for each results file that gets none.

    Learned models against move_base: in the walled environments (`fig5_must_cross.png`) where
    the must_cross study has results there, then in the open field (`fig5_baseline.png`) where
    the baseline study or must_cross's open environments have results.
    """
    summaries = data.summaries
    scalability, generalization = summaries.get("scalability", {}), summaries.get("generalization", {})
    baseline, amalgam = summaries.get("baseline", {}), summaries.get("amalgam", {})
    figures, missing = [], []
    for env in sorted({e for (_, e) in scalability} | {e for (_, e) in generalization}):
        figures.append(_figure_environment(env, scalability, generalization, figures_dir / f"fig5_{env}.png",
                                           len(figures) + 1))
    if must_cross and must_cross.walled:
        figures.append(_figure_must_cross(must_cross, figures_dir / "fig5_must_cross.png", len(figures) + 1))
    paper = must_cross.open_field(PAPER_MOVE_BASE) if must_cross else {}
    shipped = {env: models[0] for env, models in (must_cross.open_learned if must_cross else {}).items()
               if models and model_demos(models[0][0]) is None}
    if baseline or paper:
        figures.append(_figure_baseline(scalability, baseline, figures_dir / "fig5_baseline.png", len(figures) + 1,
                                        paper, shipped))
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


def _open_field_comparisons(scalability: dict, baseline: dict, must_cross: MustCross | None,
                            controller: str) -> list[Comparison]:
    """In the open field, each environment's learned models against `controller` there (the
    baseline study's `dwa`, or a controller of the must_cross study): the 40-demonstration
    model of the scalability study, and the learned models the must_cross study ran in the
    open environments (on its own seeds)."""
    if controller == DWA:
        summaries = {env: s for (label, env), s in baseline.items() if label == DWA}
    else:
        summaries = must_cross.open_field(controller) if must_cross else {}
    found = []
    for env, s in sorted(summaries.items()):
        models = [(f"{env}_40", scalability.get((f"{env}_40", env))),
                  *(must_cross.open_learned.get(env, []) if must_cross else [])]
        found += [compare(env, model, learned, controller, s) for model, learned in models]
    return [c for c in found if c is not None]


def _open_field_controllers(must_cross: MustCross | None) -> list[str]:
    """The controllers compared in the open field: the baseline study's `dwa`, then the
    must_cross study's others."""
    return [DWA, *(name for name in (must_cross.controllers if must_cross else ()) if name != DWA)]


_BEATS = "every learned model beats move_base in its own environment"


def _around_of(comparisons: list[Comparison]) -> int:
    """The classical controller's successes that went around the ditch, counted once per environment."""
    return sum({c.environment: c.baseline.around for c in comparisons}.values())


def _successes_of(comparisons: list[Comparison]) -> int:
    return sum({c.environment: c.baseline.successes for c in comparisons}.values())


def _findings(scalability: dict, generalization: dict, baseline: dict, amalgam: dict,
              must_cross: MustCross | None = None) -> list[str]:
    """The paper's findings (SPEC) beside ours; each verdict computed from the numbers."""
    rows = ["| paper's finding | ours | agree? |", "| --- | --- | --- |"]
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
    if must_cross:
        for controller in must_cross.controllers:
            comparisons = must_cross.comparisons(controller)
            if not comparisons:
                continue
            ours = _comparisons_cell(comparisons)
            around = _around_of(comparisons)
            if around:  # The walls should leave no way around: say so if some success still never entered.
                ours += (f" ({around} of {controller}'s {_successes_of(comparisons)} successes never tilted past "
                         f"{AROUND_TILT_DEG:g} deg)")
            compared = {c.environment for c in comparisons}
            unmatched = [env for env in must_cross.walled
                         if _counted(must_cross.controllers[controller].get(env)) and env not in compared]
            if unmatched:
                ours += f"; no learned model evaluated in {', '.join(unmatched)}"
            rows.append(f"| {_BEATS}: walled (every route crosses the ditch), against "
                        f"{_CONTROLLER_NAMES.get(controller, controller)} | {ours} | {beats_verdict(comparisons)} |")
        rows += _backslope_row(must_cross)
    for controller in _open_field_controllers(must_cross):
        comparisons = _open_field_comparisons(scalability, baseline, must_cross, controller)
        if not comparisons:
            continue
        ours = _comparisons_cell(comparisons)
        around = _around_of(comparisons)
        if around:
            ours += (f" (but {around} of {controller}'s {_successes_of(comparisons)} successes went around the ditch, "
                     "never entering it: the open field lets it bypass the obstacle)")
        rows.append(f"| {_BEATS}: open field, against {_CONTROLLER_NAMES.get(controller, controller)} | {ours} | "
                    f"{beats_verdict(comparisons)} |")
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
    must_cross = must_cross_groups(data)
    figures, missing = _figures(data, figures_dir, must_cross)
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
        lines += _findings_section(data, must_cross)
    return atomic_write_text(out, "\n".join(lines))


def _findings_section(data: ReportData, must_cross: MustCross | None) -> list[str]:
    """The findings table, the rule of its verdicts, the pairs behind "beats move_base", and the
    must_cross study's halts by region."""
    summaries = data.summaries
    scalability, baseline = summaries.get("scalability", {}), summaries.get("baseline", {})
    findings = _findings(scalability, summaries.get("generalization", {}), baseline, summaries.get("amalgam", {}),
                         must_cross)
    lines = ["## The paper's findings and ours", ""]
    if must_cross and must_cross.walled:
        lines += [("The paper's move_base had to cross its ditches; ours can go around an open field's ditch. So "
                   "\"beats move_base\" is answered where every route crosses the ditch (the must_cross study's "
                   "walled environments: each environment's learned models, the shipped one and the paper-method "
                   "one, against the paper's move_base and our DWA there), and beside it in the open field (each "
                   "environment's learned models against the same controllers there)."), ""]
    lines += [*findings, ""]
    pairs = [(f"walled, against {controller}", must_cross.comparisons(controller))
             for controller in (must_cross.controllers if must_cross else ())]
    pairs += [(f"open field, against {controller}",
               _open_field_comparisons(scalability, baseline, must_cross, controller))
              for controller in _open_field_controllers(must_cross)]
    table = _comparisons_table([(setting, comparisons) for setting, comparisons in pairs if comparisons])
    if table:
        lines += ["### Learned models against move_base, pair by pair", "", _verdict_rule(), "", *table, ""]
    if must_cross and must_cross.controllers.get(PAPER_MOVE_BASE):
        lines += [("Backslope rule: 'yes' when more than half of dwa_paper's failures in the walled environments "
                   "ended on the up wall (the backslope) and, where the records count halts, it halted there at "
                   "least once."), ""]
    halts = _halts_table(must_cross) if must_cross else []
    if halts:
        lines += ["### Halts of the classical controllers by region (must_cross)", "",
                  ("Halts (the |v| command below 0.05 m/s for 0.5 s or more) per region of the rollout, summed "
                   "over each group's rollouts, so the paper's failure (halt to replan on the backslope, slide, "
                   "roll) is measured, not guessed."), "", *halts, ""]
    return lines
