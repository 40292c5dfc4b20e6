"""The benchmark's page: `ditch-drake benchmark-report RESULTS... --out PAGE.md`.

From benchmark results files (and the ditches file beside each, `splits.ditches_file`):
- success per controller and split, with 95 % Wilson intervals, and in each of the paper's ditches;
- time and path length of the successes, and paired with the split's most successful controller;
- success against each ditch's slope, bottom width, depth and course curvature, and each task's
  turn from square across (a figure and its tables: per controller, the rate in bins of each,
  pooled over the generated splits);
- failure regions (status @ where the robot ended) per controller;
- every failed generated ditch, with the command that replays the rollout.

A privileged controller's rows, and a clone's crossing side's source, are marked in the
controller's name (`evaluation.model_labels.controller_labels`): "expert (privileged: analytic
terrain)", "generalist (perceived side)"; records that differ in either are different rows.
"""

import itertools
import os
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ditch_drake.benchmark.run import replay_command
from ditch_drake.benchmark.splits import PAPER_SPLIT, SPLITS, ditches_file, split_of_environment
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import atomic_write_text, prepare_output, remove_stale_temporaries, save_figure
from ditch_drake.common.outputs import figures_beside, refuse_outputs_over_inputs
from ditch_drake.evaluation.batch import load_results
from ditch_drake.evaluation.model_labels import any_marked, controller_labels, marks_note
from ditch_drake.evaluation.results import RolloutRecord, current_records
from ditch_drake.evaluation.statistics import percent
from ditch_drake.evaluation.summary import summarize
from ditch_drake.world.crossing import crossing_turn_deg
from ditch_drake.world.environments import Environment, get_environment, load_environments
from ditch_drake.world.terrain import DitchTerrain

# The ditch parameters success is plotted against: (name, axis label, bin edges).
# The edges span the test ranges (ranges.yaml) and the stress split's beyond them (stress_ranges.yaml).
FEATURES = (
    ("slope_deg", "wall slope (deg)", np.array([45.0, 50.0, 55.0, 57.0, 60.0])),
    ("bottom_width_m", "bottom width or crater diameter (m)", np.array([1.5, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0])),
    ("depth_m", "depth (m)", np.array([2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0])),
    ("curvature_per_m", "course curvature (1/m; 0: straight or crater)",
     np.array([0.0, 1e-9, 0.04, 0.08, 0.2])),
    # The expert turns right along the edge within 15 deg of square (EdgeAngleDriverConfig.straight_across_deg).
    ("crossing_turn_deg", "crossing's turn from square (deg; + left)",
     np.array([-45.0, -35.0, -15.0, -5.0, 5.0, 15.0, 35.0, 45.0])),
)


def ditch_features(environment: Environment) -> dict[str, float | str]:
    """The parameters a report groups by: course kind, slope, bottom width, depth, curvature."""
    terrain = environment.terrain
    return {"course": terrain.course, "slope_deg": terrain.slope_deg, "bottom_width_m": terrain.bottom_width_m,
            "depth_m": terrain.depth_m, "curvature_per_m": DitchTerrain(terrain).max_curvature_per_m}


def _record_features(records: list[RolloutRecord], environments: dict[str, Environment],
                     ditches: dict[str, dict]) -> dict[tuple, dict]:
    """Each record's ditch's `ditches` entry (its `ditch_features`) and its task's `crossing_turn_deg`,
    by (environment, task)."""
    tasks = {(r.environment, r.task) for r in records if r.environment in environments}
    return {(name, task): {**ditches[name], "crossing_turn_deg": crossing_turn_deg(environments[name], task)}
            for name, task in tasks}


def _environments_of(results_path: Path, records: list[RolloutRecord]) -> dict[str, Environment]:
    """The generated ditches `records` (of `results_path`) ran in: from the ditches file beside
    the results, then from the files the records name (a results file moved away from its own).

    Raises:
        ConfigError: a record's ditch is in none of those files, naming them.
    """
    beside = ditches_file(results_path)
    files = [beside, *sorted({Path(r.environments_file) for r in records if r.environments_file} - {beside})]
    environments: dict[str, Environment] = {}
    for file in files:
        if file.exists():
            found = load_environments(file, prove_walls=False)
            environments.update({name: found[name] for name in found if name not in environments})
    missing = sorted({r.environment for r in records if r.environment not in environments
                      and split_of_environment(r.environment) != PAPER_SPLIT})
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise ConfigError(f"{results_path}: ditch {missing[0]}{more} is in none of {', '.join(map(str, files))} (each "
                          "missing or without it); expected the ditches file the benchmark wrote beside the results "
                          "(move it along with them)")
    return environments


def load_benchmark(results: list[str | os.PathLike]) -> tuple[list[RolloutRecord], dict[str, Environment], list[str]]:
    """The current records of the results files, the environments they ran in, and notes.

    Raises:
        ConfigError: two files ran different ditches of the same name (other ranges), a file
            with no complete record, or a ditch that no ditches file holds (`_environments_of`).
    """
    records, environments, notes = [], {}, []
    source: dict[str, Path] = {}
    for path in results:
        path = Path(path)
        file_records = load_results([path])
        if not file_records:
            raise ConfigError(f"no complete records in {path}; expected the results of `ditch-drake benchmark`")
        records += file_records
        for name, environment in _environments_of(path, file_records).items():
            if name in environments and repr(environments[name]) != repr(environment):
                raise ConfigError(f"{path}: its {name} differs from {source[name]}'s (ditches drawn from other "
                                  "ranges?): report results of one ranges file together")
            environments[name], source[name] = environment, path
    records, notes = current_records(records)
    for record in records:
        if record.environment not in environments and split_of_environment(record.environment) == PAPER_SPLIT:
            environments[record.environment] = get_environment(record.environment)
    return records, environments, notes


def _success_table(groups: dict[tuple[str, str], list[RolloutRecord]], controllers: list[str]) -> list[str]:
    splits = [split for split in SPLITS if any(key[1] == split for key in groups)]
    lines = ["| controller | " + " | ".join(splits) + " |", "| --- |" + " --- |" * len(splits)]
    for controller in controllers:
        cells = []
        for split in splits:
            group = groups.get((controller, split), [])
            if not group:
                cells.append("-")
                continue
            summary = summarize(group)
            cells.append(f"{summary.successes}/{summary.trials} ({percent(summary.rate, '-')}, "
                         f"{percent(summary.low, '-')}-{percent(summary.high, '-')})"
                         + (f", {summary.errors} errors" if summary.errors else ""))
        lines.append(f"| {controller} | " + " | ".join(cells) + " |")
    return lines


def _quartiles(values: list[float]) -> str:
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return f"{median:.0f} ({q1:.0f}-{q3:.0f})"


def _time_and_path_lines(groups: dict[tuple[str, str], list[RolloutRecord]], controllers: list[str]) -> list[str]:
    """Time and path length of the successful rollouts per controller and split, and beside the
    split's most successful controller on the rollouts (environment, task, seed) both crossed.

    Each controller crosses different ditches, and the hard ones take longer, so only the paired
    columns compare like with like.
    """
    lines = ["## Time and path length", "",
             "Of the successful rollouts: median (interquartile range). \"paired\": the median over the rollouts "
             "(same ditch, task and seed) that both this controller and the split's most successful one crossed, "
             "of this one's time and path length divided by that one's.", "",
             "| controller | split | successes | time (s) | path (m) | paired with | paired rollouts "
             "| time ratio | path ratio |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    splits = [split for split in SPLITS if any(key[1] == split for key in groups)]
    for split in splits:
        crossed = {controller: {(r.environment, r.task, r.seed): r for r in groups.get((controller, split), [])
                                if r.success} for controller in controllers}
        reference = max(controllers, key=lambda controller: len(crossed[controller]))
        for controller in controllers:
            mine = crossed[controller]
            if not mine:
                if groups.get((controller, split)):
                    lines.append(f"| {controller} | {split} | 0 | - | - | - | - | - | - |")
                continue
            cells = [str(len(mine)), _quartiles([r.time_s for r in mine.values()]),
                     _quartiles([r.path_length_m for r in mine.values()])]
            both = sorted(mine.keys() & crossed[reference].keys())
            if controller == reference or not both:
                cells += ["-", "-", "-", "-"]
            else:
                ratios = np.array([(mine[k].time_s / crossed[reference][k].time_s,
                                    mine[k].path_length_m / crossed[reference][k].path_length_m) for k in both])
                time_ratio, path_ratio = np.median(ratios, axis=0)
                cells += [reference, str(len(both)), f"{time_ratio:.2f}", f"{path_ratio:.2f}"]
            lines.append(f"| {controller} | {split} | " + " | ".join(cells) + " |")
    return lines + [""]


def _binned(records: list[RolloutRecord], features: dict[tuple, dict], name_of: Callable[[RolloutRecord], str],
            controller: str, name: str, edges: np.ndarray) -> list[tuple[int, int]]:
    """(successes, trials) of `controller`'s rollouts in each bin of their `name`
    (`_record_features`; the last bin closed; values outside go to the nearest bin)."""
    values = [(features[(r.environment, r.task)][name], r.success) for r in records
              if name_of(r) == controller and r.status != "error" and (r.environment, r.task) in features]
    counts = [(0, 0)] * (len(edges) - 1)
    for value, success in values:
        k = int(np.clip(np.digitize(value, edges) - 1, 0, len(edges) - 2))
        counts[k] = (counts[k][0] + int(success), counts[k][1] + 1)
    return counts


def _binned_tables(records: list[RolloutRecord], features: dict[tuple, dict], name_of: Callable[[RolloutRecord], str],
                   controllers: list[str]) -> list[str]:
    lines = []
    for name, label, edges in FEATURES:
        between = " to " if edges.min() < 0 else "-"  # "-5 to 5" reads better than "-5-5".
        bins = [f"{low:g}{between}{high:g}" for low, high in itertools.pairwise(edges)]
        lines += [f"| {label} | " + " | ".join(bins) + " |", "| --- |" + " --- |" * len(bins)]
        for controller in controllers:
            counts = _binned(records, features, name_of, controller, name, edges)
            lines.append(f"| {controller} | " + " | ".join(f"{ok}/{n}" if n else "-" for ok, n in counts) + " |")
        lines.append("")
    return lines


def _figure(records: list[RolloutRecord], features: dict[tuple, dict], name_of: Callable[[RolloutRecord], str],
            controllers: list[str], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(FEATURES), figsize=(4.0 * len(FEATURES), 3.6), sharey=True)
    for ax, (name, label, edges) in zip(axes, FEATURES):
        centres = (edges[:-1] + edges[1:]) / 2
        for controller in controllers:
            counts = _binned(records, features, name_of, controller, name, edges)
            if not any(n for _, n in counts):
                continue
            ax.plot(centres, [ok / n if n else np.nan for ok, n in counts], marker="o", label=controller)
        ax.set_xlabel(label)
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate")
    axes[-1].legend(fontsize=7, loc="lower left")
    fig.suptitle("Success against the ditch's parameters and the crossing's turn (generated splits pooled)")
    fig.tight_layout()
    return save_figure(fig, path)


def _side_agreement_lines(records: list[RolloutRecord], environments: dict[str, Environment],
                          name_of: Callable[[RolloutRecord], str]) -> list[str]:
    """The section on a perceived crossing side against the oracle's (`RolloutRecord`'s side_*
    fields), if any record has one: the approach zone's steps that agree, per controller and
    split and per course kind, and every rollout where they did not."""
    measured = [r for r in records if r.crossing_side_source == "perceived" and r.status != "error"]
    if not measured:
        return []

    def share(group: list[RolloutRecord]) -> str:
        zone = sum(r.side_zone_steps for r in group)
        agreeing = sum(r.side_agreeing_steps for r in group)
        whole = sum(r.side_agreeing_steps == r.side_zone_steps for r in group)
        rate = f"{100.0 * agreeing / zone:.2f} %" if zone else "-"  # 98 % is the target: whole percents hide it.
        return f"{agreeing}/{zone} ({rate}); {whole}/{len(group)}"

    def kind(record: RolloutRecord) -> str:
        environment = environments.get(record.environment)
        return environment.terrain.course if environment is not None else "?"

    kinds = sorted({kind(r) for r in measured})
    lines = ["## The perceived crossing side against the oracle's", "",
             ("Control steps in the approach zone (the oracle's: from where the chassis first came within the "
             "expert's approach margin of the hinge line) where the side the clone was told, perceived from the "
             "lidar, equals the oracle's from the ditch's course; then rollouts whose every such step agrees; "
             "in all and per course kind."), "",
             "| controller | split | all | " + " | ".join(kinds) + " |",
             "| --- | --- | --- |" + " --- |" * len(kinds)]
    by_group: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    for record in measured:
        by_group[(name_of(record), split_of_environment(record.environment))].append(record)
    for (controller, split), group in sorted(by_group.items()):
        cells = [share([r for r in group if kind(r) == name]) if any(kind(r) == name for r in group) else "-"
                 for name in kinds]
        lines.append(f"| {controller} | {split} | {share(group)} | " + " | ".join(cells) + " |")
    differing = [r for r in measured if r.side_agreeing_steps < r.side_zone_steps]
    lines.append("")
    if differing:
        lines += [("Rollouts where they differed (distance to the hinge line of the differing steps, m; negative: "
                  "inside it):"), "",
                  ("| controller | environment | task | seed | course | crossing turn (deg) | agreeing steps | "
                  "told none | distance to the edge | outcome |"),
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for record in sorted(differing, key=lambda r: (name_of(r), r.environment, r.task, r.seed)):
            environment = environments.get(record.environment)
            turn = f"{crossing_turn_deg(environment, record.task):+.0f}" if environment is not None else "?"
            edge = ("{:+.1f} to {:+.1f}".format(*record.side_disagreement_edge_m)
                    if len(record.side_disagreement_edge_m) == 2 else "-")
            lines.append(f"| {name_of(record)} | {record.environment} | {record.task} | {record.seed} | {kind(record)} "
                         f"| {turn} | {record.side_agreeing_steps}/{record.side_zone_steps} | "
                         f"{record.side_unseen_steps} | {edge} | {record.status} |")
        lines.append("")
    return lines


def write_benchmark_report(results: list[str | os.PathLike], out: str | os.PathLike,
                           figures_dir: str | os.PathLike | None = None, title: str = "Procedural ditch benchmark",
                           command: str = "") -> Path:
    """Writes the page (and its figure) from benchmark results files; returns the page's path.

    Raises:
        ConfigError: a results file that cannot be read, or a page or figures folder that
            cannot be written, or that is one of `results` or the ditches file beside one
            (`common.outputs.refuse_outputs_over_inputs`; nothing is written), naming the path.
    """
    figures = Path(figures_dir) if figures_dir else figures_beside(out)
    refuse_outputs_over_inputs({"report page": out, "figures folder": figures},
                               [*results, *map(ditches_file, results)], recursive=True)
    out = prepare_output(out, "report page")
    records, environments, notes = load_benchmark(results)
    remove_stale_temporaries(out.parent)  # A killed run's half-written page or figure.
    remove_stale_temporaries(figures)
    groups: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    name_of = controller_labels(records)
    for record in records:
        groups[(name_of(record), split_of_environment(record.environment))].append(record)
    controllers = sorted({key[0] for key in groups})
    generated = [r for r in records if split_of_environment(r.environment) not in ("", PAPER_SPLIT)]
    if generated:  # Only a page with a figure needs the folder: none is made for one without.
        prepare_output(figures, "figures folder", folder=True)
    ditches = {name: ditch_features(env) for name, env in environments.items()}
    features = _record_features(generated, environments, ditches)
    lines = [f"# {title}", ""]
    if command:
        lines += ["Made by", "", f"    {command}", ""]
    lines += ["## Success per split", "",
              "successes/trials (rate, 95 % Wilson interval); the test split is reported, never tuned on.", ""]
    if any_marked(records):
        lines += [marks_note(records), ""]
    lines += _success_table(groups, controllers) + [""]
    lines += _time_and_path_lines(groups, controllers)
    lines += _side_agreement_lines(records, environments, name_of)
    by_kind: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
    for record in generated:
        by_kind[(name_of(record), str(ditches[record.environment]["course"]))].append(record)
    kinds = sorted({kind for _, kind in by_kind})
    if kinds:
        lines += ["## Success per course kind (generated splits pooled)", "",
                  "| controller | " + " | ".join(kinds) + " |", "| --- |" + " --- |" * len(kinds)]
        for controller in controllers:
            cells = []
            for kind in kinds:
                summary = summarize(by_kind.get((controller, kind), [])) if by_kind.get((controller, kind)) else None
                cells.append(f"{summary.successes}/{summary.trials}" if summary else "-")
            lines.append(f"| {controller} | " + " | ".join(cells) + " |")
        lines.append("")
    paper = [r for r in records if split_of_environment(r.environment) == PAPER_SPLIT]
    if paper:
        by_environment: dict[tuple[str, str], list[RolloutRecord]] = defaultdict(list)
        for record in paper:
            by_environment[(name_of(record), record.environment)].append(record)
        names = sorted({name for _, name in by_environment})
        lines += ["## Success in each of the paper's ditches", "",
                  "| controller | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
        for controller in sorted({controller for controller, _ in by_environment}):
            cells = []
            for name in names:
                group = by_environment.get((controller, name))
                summary = summarize(group) if group else None
                cells.append(f"{summary.successes}/{summary.trials} ({percent(summary.low, '-')}-{percent(summary.high, '-')})"
                             if summary else "-")
            lines.append(f"| {controller} | " + " | ".join(cells) + " |")
        lines.append("")
    if generated:
        figure = _figure(generated, features, name_of, controllers, figures / "benchmark_success_by_parameter.png")
        lines += ["## Success against the ditch's parameters", "",
                  f"![success against slope, width, depth, curvature, crossing turn]({os.path.relpath(figure, out.parent)})",
                  "",
                  "The figure's numbers: successes/trials in each bin (generated splits pooled).", ""]
        lines += _binned_tables(generated, features, name_of, controllers)
    lines += ["## Failure regions", "", "status@region of the failed rollouts (the region where the robot ended).", "",
              "| controller | split | failures |", "| --- | --- | --- |"]
    for (controller, split), group in sorted(groups.items()):
        regions = summarize(group).failure_regions
        text = ", ".join(f"{name} {count}" for name, count in sorted(regions.items(), key=lambda item: -item[1]))
        lines.append(f"| {controller} | {split} | {text or '-'} |")
    lines += ["", "## Failed generated ditches", "",
              "Each replays as a standalone HTML page with the command beside it.", "",
              "| controller | ditch (seed) | task | rollout seed | status@region | parameters | replay |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for record in sorted(generated, key=lambda r: (name_of(r), r.environment, r.task, r.seed)):
        if record.success:
            continue
        feature = features[(record.environment, record.task)]
        parameters = (f"{feature['course']}, {feature['slope_deg']:.1f} deg, {feature['bottom_width_m']:.1f} m wide, "
                      f"{feature['depth_m']:.1f} m deep, turned {feature['crossing_turn_deg']:+.0f} deg")
        replay = f"`{replay_command(record)}`"
        lines.append(f"| {name_of(record)} | {record.environment} | {record.task} | {record.seed} | "
                     f"{record.status}@{record.failure_region} | {parameters} | {replay} |")
    if notes:
        lines += ["", "## Notes", ""] + [f"- {note}" for note in notes]
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "\n".join(lines) + "\n")
    return out
