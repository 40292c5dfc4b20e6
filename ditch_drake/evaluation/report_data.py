"""What a results page summarises: the current records of each results file, grouped by study,
with their summaries and tables (`load_report_data`).

A study is recognized from a results file's name (`scalability.jsonl`, ...); any other file is
a study of its own, under its name. Only the current records count (`results.current_records`):
one per rollout key (a real outcome beats an error record), and per learned checkpoint name only
the records of the file as it is now where it still resolves. What was set aside is a note.

A results file with records of the `shared` controller also gets a table of how much its
fallback drove (`shared_control_table`).
"""

import os
import statistics
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from ditch_drake.evaluation.model_labels import controller_labels
from ditch_drake.evaluation.results import RolloutRecord, current_records, read_records
from ditch_drake.evaluation.statistics import percent
from ditch_drake.evaluation.summary import GroupSummary, summarize

# The paper's studies, in its order: the results files of these names are read as theirs.
STUDIES = ("scalability", "generalization", "baseline", "amalgam", "must_cross")


@dataclass
class ReportData:
    """What a results page summarises.

    Attributes:
        records: the current records of each study (results file name), in file order.
        notes: what was set aside or could not be read, one sentence each.
        summaries: per study, a `GroupSummary` per (model, environment).
        tables: per study, its Markdown table's lines.
        shared_tables: per study with records of the `shared` controller, the lines of its
            "Shared control" table (`shared_control_table`); other studies are absent.
    """

    records: dict[str, list[RolloutRecord]]
    notes: list[str] = field(default_factory=list)
    summaries: dict[str, dict[tuple[str, str], GroupSummary]] = field(default_factory=dict)
    tables: dict[str, list[str]] = field(default_factory=dict)
    shared_tables: dict[str, list[str]] = field(default_factory=dict)

    @property
    def studies(self) -> list[str]:
        """The paper's studies present, in the paper's order, then the other files' names."""
        return [*(study for study in STUDIES if study in self.records), *sorted(set(self.records) - set(STUDIES))]

    def study_lines(self, study: str) -> list[str]:
        """A study's table, then its "Shared control" table where it has one."""
        shared = self.shared_tables.get(study)
        return [*self.tables[study], *(["", "### Shared control", "", *shared] if shared else [])]

    def markdown_tables(self) -> str:
        """Every study's tables under its name (what `ditch-drake report` prints)."""
        return "\n".join(f"## {study}\n\n" + "\n".join(self.study_lines(study)) + "\n" for study in self.studies)


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
        data.tables[study], data.summaries[study] = study_table(data.records[study])
        shared = shared_control_table(data.records[study])
        if shared:
            data.shared_tables[study] = shared
    return data


def study_table(records: list[RolloutRecord]) -> tuple[list[str], dict[tuple[str, str], GroupSummary]]:
    """A study's Markdown table (one row per model and environment: successes, Wilson interval,
    failures by status and region, halts by region, errors, the successes' median time and path
    length) and the summaries behind it. A model's rollouts in generated ditches (a benchmark
    split's) are one row, `pool_generated_ditches`."""
    groups: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    name_of = controller_labels(records)
    for record in records:
        groups[(name_of(record), record.environment)].append(record)
    groups = pool_generated_ditches(groups)
    summaries = {key: summarize(group) for key, group in sorted(groups.items())}
    lines = [("| model | environment | success | rate | 95 % Wilson | of which around the ditch | "
              "failures (status@region) | halts (region) | errors | time (s) | path (m) |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (model, env), s in summaries.items():
        failures = ", ".join(f"{k} {v}" for k, v in sorted(s.failure_regions.items())) or "-"
        # The regions a crossing meets, in order; "-": records from before halts were counted.
        halts = ", ".join(f"{k} {v}" for k, v in s.halts_by_region.items() if v) or ("0" if s.halts_counted else "-")
        if 0 < s.halts_counted < s.trials:
            halts += f" (in {s.halts_counted} of {s.trials} trials)"
        crossed = [r for r in groups[(model, env)] if r.success]
        time_and_path = (f"{statistics.median(r.time_s for r in crossed):.0f} | "
                         f"{statistics.median(r.path_length_m for r in crossed):.0f}" if crossed else "- | -")
        lines.append(f"| {model} | {env} | {s.successes}/{s.trials} | {percent(s.rate)} | "
                     f"{percent(s.low)}-{percent(s.high)} | {s.around} | {failures} | {halts} | {s.errors} | "
                     f"{time_and_path} |")
    return lines, summaries


# The shared-control table's row of a model's rollouts in all its environments.
POOLED = "all"


def pool_generated_ditches(groups: dict[tuple[str, str], list[RolloutRecord]]) -> dict[tuple[str, str], list]:
    """`groups` (records by model and environment) with each model's groups in generated ditches
    (environments read from a benchmark run's ditches file) pooled into one, named "N generated
    ditches": a split's hundred ditches are one row a reader can take in, and `ditch-drake
    benchmark-report` is the page for them ditch by ditch."""
    from ditch_drake.world.ditch_splits import is_ditches_file

    pooled: dict[tuple[str, str], list[RolloutRecord]] = {}
    generated: dict[str, list[RolloutRecord]] = defaultdict(list)
    ditches: dict[str, set[str]] = defaultdict(set)
    for (model, env), group in groups.items():
        if group and all(is_ditches_file(record.environments_file) for record in group):
            generated[model] += group
            ditches[model].add(env)
        else:
            pooled[(model, env)] = group
    for model, group in generated.items():
        count = len(ditches[model])
        pooled[(model, f"{count} generated ditch{'es' if count > 1 else ''}")] = group
    return pooled


def is_shared_control(record: RolloutRecord) -> bool:
    """Whether `record` is a rollout of a gated policy with a fallback (the `shared` controller,
    or any record whose fallback drove some of its steps)."""
    return record.controller == "shared" or record.handover_fraction > 0


def shared_control_table(records: list[RolloutRecord]) -> list[str]:
    """How much the fallback drove, one row per model and environment with shared-control
    records: successes, the mean and largest share of control steps the fallback drove, the
    median number of switches (handovers plus handbacks) per rollout, where the handovers began
    (region:count, by region name), and the failures, with how many of them ended with the
    fallback driving (an odd number of switches: the policy drives first); error records are
    left out. A model with records in more than one environment has a first row "all", its
    rollouts pooled; its rollouts in generated ditches are one row (`pool_generated_ditches`).
    Empty without shared-control records."""
    name_of = controller_labels(records)
    groups: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    for record in records:
        if is_shared_control(record):
            groups[(name_of(record), record.environment)].append(record)
    if not groups:
        return []
    groups = pool_generated_ditches(groups)
    environments = Counter(model for model, _ in groups)
    pooled = {(model, POOLED): [record for (name, _), group in groups.items() if name == model for record in group]
              for model, count in environments.items() if count > 1}
    groups = {**pooled, **groups}
    lines = [("| model | environment | success | fallback's share of steps (mean) | (max) | switches (median) | "
              "handovers (region:count) | failures (of them, the fallback driving at the end) |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (model, env), group in sorted(groups.items(), key=lambda item: (item[0][0], item[0][1] != POOLED, item[0][1])):
        trials = [record for record in group if not record.is_error]
        successes = sum(record.success for record in trials)
        if trials:
            fractions = [record.handover_fraction for record in trials]
            mean, most = f"{100 * statistics.fmean(fractions):.1f}%", f"{100 * max(fractions):.1f}%"
            switches = f"{statistics.median(record.switches for record in trials):g}"
        else:
            mean = most = switches = "n/a"
        regions = Counter(region for record in trials for region in record.handover_regions)
        handovers = ", ".join(f"{region}:{count}" for region, count in sorted(regions.items())) or "-"
        failures = [record for record in trials if not record.success]
        under_fallback = sum(record.switches % 2 == 1 for record in failures)
        failed = f"{len(failures)} ({under_fallback})" if failures else "0"
        lines.append(f"| {model} | {env} | {successes}/{len(trials)} | {mean} | {most} | {switches} | {handovers} "
                     f"| {failed} |")
    return lines


# The series of a panel of `handover_curves` that is the policy ungated, at a share of 0.
ALONE = "alone"


@dataclass
class HandoverPoint:
    """One run of a gated policy in `handover_curves` (or the policy alone, at share 0).

    Attributes:
        share: the fallback's share of the control steps, the mean over the run's rollouts.
        summary: its successes, trials and Wilson interval.
        budget: the budget that set the gate's thresholds, None for fixed ones (or alone).
    """

    share: float
    summary: GroupSummary
    budget: float | None = None


def handover_panel(record: RolloutRecord, name: str) -> str:
    """Which panel of `handover_curves` a record of the policy `name` belongs to: the policy, its
    crossing side's source, and where it drove (a packaged environment, or a generated split)."""
    from ditch_drake.world.ditch_splits import is_ditches_file, split_of_environment

    side = f" ({record.crossing_side_source} side)" if record.crossing_side_source else ""
    split = split_of_environment(record.environment) if is_ditches_file(record.environments_file) else ""
    where = f"the {split} split" if split else record.environment
    return f"{name}{side} on {where}"


def handover_curves(records_by_study: dict[str, list[RolloutRecord]]) -> dict[str, dict[str, list[HandoverPoint]]]:
    """Success against the fallback's share of the steps: per panel (a gated policy where it
    drove, `handover_panel`), per series (the gate's signal and fallback, e.g. "tip_risk_ahead,
    fallback expert (privileged: analytic terrain)", marked as a table marks the row), one point
    per run (the records of one gate's config in one results file), in order of share; and the series `ALONE`, the same policy's ungated records in the
    same place, where the results hold them. Error records count nowhere; a panel without any
    gated run is left out."""
    from ditch_drake.diagrams.controllers import privileged_words
    from ditch_drake.evaluation.model_labels import (
        fallback_words,
        gate_budget,
        gate_settings,
        gate_words,
        hold_words,
        signal_words,
        watchdog_words,
    )

    every = [record for records in records_by_study.values() for record in records]
    name_of = controller_labels(every, marks=False)
    runs: dict[tuple[str, str, str, str], list[RolloutRecord]] = defaultdict(list)
    alone: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    for study, records in records_by_study.items():
        for record in records:
            if record.is_error:
                continue
            panel = handover_panel(record, name_of(record))
            if is_shared_control(record):
                gate = gate_settings(record)
                series = (f"{signal_words(record, gate)}{hold_words(gate)}{watchdog_words(gate)}, "
                          f"fallback {fallback_words(record, gate)}" if gate else record.controller)
                if record.privileged:
                    series += f" (privileged: {privileged_words(record.privileged)})"
                runs[(panel, series, gate_words(record), study)].append(record)
            elif record.controller == "learned":
                alone[(panel, study)].append(record)
    curves: dict[str, dict[str, list[HandoverPoint]]] = defaultdict(lambda: defaultdict(list))
    for (panel, series, _, _), group in runs.items():
        share = statistics.fmean(record.handover_fraction for record in group)
        curves[panel][series].append(HandoverPoint(share, summarize(group), gate_budget(gate_settings(group[0]))))
    for (panel, _), group in alone.items():
        if panel in curves:
            curves[panel][ALONE].append(HandoverPoint(0.0, summarize(group)))
    return {panel: {series: sorted(points, key=lambda point: point.share) for series, points in sorted(panel_series.items())}
            for panel, panel_series in sorted(curves.items())}
