"""The results page: success rates with Wilson intervals, failures, Figure 5-style plots, and
the paper's findings beside ours.

`write_report(results, out, figures_dir)` reads every results file (JSON Lines from
`evaluate` / `experiment`), keeps the current records of each (`report_data.load_report_data`),
groups them by study, and writes a Markdown page with

- the wall time of each `ditch-drake experiment` run that made the results;
- what was set aside (records not counted);
- one table per study: model, environment, successes / trials, rate and 95 % Wilson
  interval, failures by status and region, halts by region (`report_data.study_table`); a
  privileged controller's rows, and a clone's crossing side's source, marked in the model's
  name (`model_labels.controller_labels`); under a study with records of the `shared`
  controller, a "Shared control" table of how much its fallback drove
  (`report_data.shared_control_table`);
- where each evaluated checkpoint came from;
- the figures (`report_figures`), each with a caption under it;
- the paper's stated findings beside ours, each marked as agreeing or not by a rule computed
  from the numbers, never by hand (`paper_findings`), when at least one of the paper's studies
  is present.

Where the page goes by default, and the refusal to write it over its own results, are
`ditch_drake.common.outputs`'.
"""

import os
from pathlib import Path

from ditch_drake.common.files import atomic_write_text, remove_stale_temporaries
from ditch_drake.common.outputs import refuse_outputs_over_inputs
from ditch_drake.evaluation.model_labels import any_marked, controller_labels, marks_note
from ditch_drake.evaluation.paper_findings import findings_section, must_cross_groups
from ditch_drake.evaluation.report_data import STUDIES, ReportData, load_report_data
from ditch_drake.evaluation.report_figures import draw_figures
from ditch_drake.evaluation.results import RolloutRecord
from ditch_drake.evaluation.runs import RUNS_FILE, read_runs


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
        ConfigError: the page or the figures folder is one of `results`, or a results file in one
            of its folders (`common.outputs.refuse_outputs_over_inputs`); nothing is written.
        ResultsError: a line that is not a record (from `read_records`).
    """
    refuse_outputs_over_inputs({"page": out, "figures folder": figures_dir}, results, ("*.jsonl", RUNS_FILE))
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
    every_record = [record for records in data.records.values() for record in records]
    if any_marked(every_record):
        lines += [marks_note(every_record), ""]
    for study in data.studies:
        lines += [f"## {study}", "", *data.study_lines(study), ""]
    must_cross = must_cross_groups(data)
    figures, missing = draw_figures(data, figures_dir, must_cross)
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
        lines += findings_section(data, must_cross)
    return atomic_write_text(out, "\n".join(lines))


def _runs_section(results: list[str | os.PathLike]) -> list[str]:
    """A table of the `ditch-drake experiment` runs recorded in the results folders (see
    `runs.record_run`): each stage's wall time; empty if none is recorded."""
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
    (and still the file the rollouts used: same hash prefix); an ensemble's row summarises its
    members (`_ensemble_row`), an ONNX policy's names what it was exported from (`_onnx_row`)."""
    from ditch_drake.common.errors import CheckpointError, ConfigError
    from ditch_drake.learning.checkpoint import checkpoint_digest, load_checkpoint, resolve_checkpoint_path
    from ditch_drake.learning.ensemble import is_ensemble_checkpoint, load_ensemble
    from ditch_drake.learning.onnx_policy import is_onnx_path, read_onnx_policy

    lines = ["| model | checkpoint | sha256 | demonstrations (train/val) | epochs (best) | device | training_s |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    name_of = controller_labels(records, marks=False)
    used = sorted({(name_of(r), r.checkpoint, r.checkpoint_sha256) for r in records if r.checkpoint})
    for label, path, digest in used:
        row = ["(file gone or changed since)"] + [""] * 3
        try:
            if checkpoint_digest(path) == digest:
                file = resolve_checkpoint_path(path)
                if is_onnx_path(file):
                    row = _onnx_row(read_onnx_policy(file).metadata)
                elif is_ensemble_checkpoint(file):
                    row = _ensemble_row(load_ensemble(file).members)
                else:
                    summary = load_checkpoint(file).summary()
                    row = [summary["demos_train/val"], f"{summary['epochs']} ({summary['best_epoch']})",
                           summary["device"], summary["training_s"]]
        except (CheckpointError, ConfigError, OSError):
            pass
        lines.append(f"| {label} | {path} | {digest} | " + " | ".join(row) + " |")
    return lines if used else []


def _onnx_row(metadata: dict) -> list[str]:
    """An ONNX policy's Models cells from its metadata: the checkpoint it was exported from (and
    that checkpoint's hash prefix), and its quantization with the calibration samples."""
    source = f"ONNX of {metadata.get('source_checkpoint') or '?'} ({metadata.get('source_checkpoint_sha256', '')[:16]})"
    quantization = metadata.get("quantization")
    numbers = (f"{quantization.get('scheme')}, {quantization.get('calibration_samples')} calibration samples"
               if quantization else "float32")
    return [source, "-", numbers, "-"]


def _ensemble_row(members: list) -> list[str]:
    """An ensemble's Models cells from its members (`PolicyCheckpoint`s): each member's
    demonstrations (train/val) and epochs (best), "each" where all members agree; their devices;
    their training seconds summed."""
    def each(values: list[str]) -> str:
        return f"{values[0]} each" if len(set(values)) == 1 else ", ".join(values)

    summaries = [member.summary() for member in members]
    training_s = sum(float(member.metrics.get("training_seconds", float("nan"))) for member in members)
    return [f"ensemble of {len(members)}: " + each([summary["demos_train/val"] for summary in summaries]),
            each([f"{summary['epochs']} ({summary['best_epoch']})" for summary in summaries]),
            ", ".join(sorted({summary["device"] for summary in summaries})),
            f"{training_s:.0f} (sum)"]
