"""The experiment pipeline end to end on a tiny experiment, its file checks, and the report."""

import json
from collections import Counter
from dataclasses import replace
from pathlib import Path

import pytest

from ditch_drake.evaluation.report import write_report
from ditch_drake.evaluation.results import read_records
from ditch_drake.evaluation.runs import read_runs
from ditch_drake.pipelines.experiment import (
    ModelSpec,
    code_revision,
    evaluation_specs,
    load_experiment,
    model_path,
    plan,
    run_experiment,
)
from ditch_drake.world.environments import ConfigError

TINY = """
name: tiny
seed: 0
demos_dir: {root}/demos
models_dir: {root}/models
results_dir: {root}/results
report: {root}/docs/results.md
figures_dir: {root}/docs/img
tasks: [0]
rollouts: 1
time_limit_s: 2.0
workers: 1
training: {{epochs: 1, patience: 1, batches_per_epoch: 2, synthetic_fraction: 0.5}}
studies:
  scalability: {{environments: [wide], demos: [2]}}
  baseline: {{environments: [wide]}}
"""


@pytest.fixture
def tiny_experiment(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.format(root=tmp_path))
    return path


def page_row(tmp_path) -> str:
    (row,) = [line for line in (tmp_path / "docs" / "results.md").read_text().splitlines()
              if "`ditch-drake experiment tiny.yaml`" in line]
    return row


def test_code_revision_names_a_commit_or_the_version():
    import re

    import ditch_drake

    assert re.fullmatch(r"[0-9a-f]{12}(\+changes)?", code_revision()) or code_revision() == (
        f"ditch_drake {ditch_drake.__version__}")


def test_a_tiny_experiment_runs_end_to_end_and_a_rerun_redoes_nothing(tmp_path, tiny_experiment):
    config = load_experiment(tiny_experiment)
    timings = run_experiment(config, progress=False, command="ditch-drake experiment tiny.yaml")
    assert set(timings) == {"collect_s", "train_s", "evaluate_s", "report_s"}
    (run,) = read_runs(tmp_path / "results")
    assert {key: run[key] for key in timings} == timings and run["command"] == "ditch-drake experiment tiny.yaml"
    assert run["code"] == code_revision() and run["code"] in page_row(tmp_path)
    assert len(list((tmp_path / "demos" / "wide").glob("episodes/episode_*"))) == 2
    assert (tmp_path / "models" / "wide_2.pt").exists()
    records = {study: read_records(tmp_path / "results" / f"{study}.jsonl")[0] for study in ("scalability", "baseline")}
    assert [r.controller for r in records["scalability"]] == ["learned"]
    assert [r.controller for r in records["baseline"]] == ["dwa"]
    assert all(r.status != "error" for rs in records.values() for r in rs), records
    page = (tmp_path / "docs" / "results.md").read_text()
    assert "| wide_2 | wide | 0/1 |" in page and "| dwa | wide |" in page
    # The page was written during the report stage: this run's other stages are timed, the report is not.
    (row,) = [line for line in page.splitlines() if "`ditch-drake experiment tiny.yaml`" in line]
    assert row.rstrip(" |").split(" | ")[-2] == "-" and f"| {timings['collect_s']:.0f} |" in row
    assert (tmp_path / "docs" / "img" / "fig5_wide.png").stat().st_size > 1000
    assert (tmp_path / "docs" / "img" / "fig5_baseline.png").stat().st_size > 1000

    model_time = (tmp_path / "models" / "wide_2.pt").stat().st_mtime_ns
    run_experiment(config, stages=("collect", "train", "evaluate"), progress=False)
    assert (tmp_path / "models" / "wide_2.pt").stat().st_mtime_ns == model_time
    assert len(read_records(tmp_path / "results" / "scalability.jsonl")[0]) == 1
    assert len(read_runs(tmp_path / "results")) == 2 and "report_s" not in read_runs(tmp_path / "results")[1]

    (tmp_path / "results" / "experiment_runs.json").write_text("{not json")
    with pytest.raises(ConfigError, match="experiment_runs.json: not JSON"):
        read_runs(tmp_path / "results")


def test_experiment_files_with_a_typo_or_an_unknown_environment_are_refused(tmp_path, tiny_experiment):
    typo = tmp_path / "typo.yaml"
    typo.write_text(tiny_experiment.read_text().replace("rollouts: 1", "rolouts: 1"))
    with pytest.raises(ConfigError, match="rolouts"):
        load_experiment(typo)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text(tiny_experiment.read_text().replace("[wide], demos", "[wide, moon], demos"))
    with pytest.raises(ConfigError, match="'moon'"):
        load_experiment(unknown)
    with pytest.raises(ConfigError, match="cannot read"):
        load_experiment(tmp_path / "missing.yaml")
    fp16 = tmp_path / "fp16.yaml"
    fp16.write_text(tiny_experiment.read_text().replace("synthetic_fraction: 0.5}", "synthetic_fraction: 0.5, precision: fp16}"))
    with pytest.raises(ConfigError, match="training.precision='fp16'"):
        load_experiment(fp16)
    smote2 = tmp_path / "smote2.yaml"
    smote2.write_text(tiny_experiment.read_text().replace("synthetic_fraction: 0.5}", "synthetic_fraction: 0.5, balancing: smote2}"))
    with pytest.raises(ConfigError, match="training.balancing='smote2': expected one of"):
        load_experiment(smote2)
    for method in ("smote", "oversample", "weighted_sampler", "class_weights", "ordinal_soft_labels"):
        balancing = load_experiment(f"experiments/balancing/{method}.yaml")
        assert balancing.training.balancing == method and balancing.studies.scalability.demos == [40]


def test_the_paper_protocol_plans_13_models_and_29_evaluations_and_32_where_the_ditch_must_be_crossed():
    config = load_experiment("experiments/paper.yaml")
    models, evaluations = plan(config)
    # 4 x (10, 20, 40) + the amalgam; must_cross's 40-demonstration models are among them (+ shared_control's
    # ensembles, and its clones retrained after the aggregation round, four per environment).
    assert len([m for m in models if m.ensemble == 1 and m.intervention_weight is None]) == 13
    assert len([m for m in models if m.intervention_weight is not None]) == 16
    studies = Counter(e.study for e in evaluations)
    assert studies == {"scalability": 12, "generalization": 12, "baseline": 4, "amalgam": 1, "must_cross": 32,
                       "shared_control": 104}
    models, evaluations = plan(config, only=["wide"])
    assert {m.name for m in models} >= {"wide_10", "wide_20", "wide_40", "crater+narrow+sine_40"}
    assert all("wide" in (e.environment, e.environment.removesuffix("_walled"),
                          *(e.model.environments if e.model else ())) for e in evaluations)


WALLED = ["crater_walled", "wide_walled", "narrow_walled", "sine_walled"]
OPEN = ["crater", "wide", "narrow", "sine"]


def test_must_cross_runs_both_dwas_the_mppi_and_both_learned_models_in_every_walled_environment_and_more_in_the_open():
    config = load_experiment("experiments/paper.yaml")
    _, evaluations = plan(config)
    must_cross = [e for e in evaluations if e.study == "must_cross"]
    walled = [e for e in must_cross if e.environment in WALLED]
    # Per walled environment: dwa, dwa_paper, mppi, the shipped model (no model to train) and the paper-method one.
    assert Counter(e.environment for e in walled) == dict.fromkeys(WALLED, 5)
    for env, base in zip(WALLED, OPEN):
        here = [(e.controller, e.model) for e in walled if e.environment == env]
        assert here == [("dwa", None), ("dwa_paper", None), ("mppi", None), ("learned", None),
                        ("learned", ModelSpec((base,), 40))]
    # Each paper-method model is the experiment's own file, the one the generalization study trains.
    paths = {model_path(config, e.model) for e in walled if e.model}
    assert paths == {Path("models/paper") / f"{env}_40.pt" for env in OPEN}
    generalization = {e.model for e in evaluations if e.study == "generalization"}
    assert {e.model for e in walled if e.model} <= generalization
    # The open field on the same seeds: the paper's move_base, the MPPI and the shipped models.
    assert [(e.controller, e.environment) for e in must_cross if e.environment in OPEN] == [
        (controller, env) for env in OPEN for controller in ("dwa_paper", "mppi", "learned")]
    # 3 tasks x 10 rollouts each; the shipped model is the walled environment's base's.
    shipped = next(e for e in walled if e.controller == "learned" and e.model is None and e.environment == "wide_walled")
    specs = evaluation_specs(config, shipped)
    assert len(specs) == 30 and {s.checkpoint for s in specs} == {"wide"} and {s.task for s in specs} == {0, 1, 2}
    dwa_paper = evaluation_specs(config, next(e for e in walled if e.controller == "dwa_paper"))
    assert len(dwa_paper) == 30 and {s.controller for s in dwa_paper} == {"dwa_paper"}


def test_only_an_open_environment_keeps_its_walled_variant_and_an_untrained_model_is_skipped(tmp_path):
    config = load_experiment("experiments/paper.yaml")
    config = replace(config, models_dir=str(tmp_path / "models"),
                     studies=replace(config.studies, scalability=None, generalization=None, baseline=None, amalgam=None,
                                     shared_control=None))
    models, evaluations = plan(config, only=["wide"])
    assert models == [ModelSpec(("wide",), 40)]  # The train stage trains it when it is missing.
    assert [(e.controller, e.environment) for e in evaluations] == [
        ("dwa", "wide_walled"), ("dwa_paper", "wide_walled"), ("mppi", "wide_walled"), ("learned", "wide_walled"),
        ("learned", "wide_walled"), ("dwa_paper", "wide"), ("mppi", "wide"), ("learned", "wide")]
    models, evaluations = plan(config, only=["wide_walled"])
    assert models == [ModelSpec(("wide",), 40)] and {e.environment for e in evaluations} == {"wide_walled"}
    untrained = next(e for e in evaluations if e.model)
    assert evaluation_specs(config, untrained) == []  # Not trained yet: the evaluate stage says so and goes on.


def test_a_must_cross_study_naming_an_open_environment_or_an_unknown_controller_is_refused(tmp_path, tiny_experiment):
    text = tiny_experiment.read_text()
    cases = {"open": ("{environments: [wide]}", "are not walled variants"),
             "controller": ("{environments: [wide_walled], controllers: [dwa, move_base]}", "'move_base'"),
             "demos": ("{environments: [wide_walled], demos: -1}", "demos=-1")}
    for name, (study, message) in cases.items():
        path = tmp_path / f"{name}.yaml"
        path.write_text(text + f"  must_cross: {study}\n")
        with pytest.raises(ConfigError, match=message):
            load_experiment(path)
    path = tmp_path / "fine.yaml"
    path.write_text(text + "  must_cross: {environments: [wide_walled], open_environments: [wide]}\n")
    study = load_experiment(path).studies.must_cross
    assert (study.controllers, study.open_controllers, study.shipped_models, study.demos) == (
        ["dwa", "dwa_paper"], ["dwa_paper"], True, 40)


def test_the_report_renders_from_a_small_fixture(tmp_path):
    base = {"schema": "ditch_drake.rollout_record", "schema_version": 2, "checkpoint_sha256": "", "task": 0,
            "time_limit_s": 120.0, "goal_radius_m": 1.5, "time_s": 50.0, "path_length_m": 20.0, "peak_abs_roll_deg": 10.0,
            "peak_abs_pitch_deg": 30.0, "peak_tilt_deg": 31.0, "min_stability_margin_deg": 20.0, "final_x_m": 0.0,
            "final_y_m": 0.0, "wall_s": 5.0, "error": ""}

    def rows(controller, checkpoint, env, outcomes):
        return [dict(base, key=f"{controller}{checkpoint}{env}{i}", controller=controller, checkpoint=checkpoint,
                     environment=env, seed=i, status=status, success=status == "reached_goal",
                     failure_region="" if status == "reached_goal" else region)
                for i, (status, region) in enumerate(outcomes)]

    ok, rolled = ("reached_goal", ""), ("rolled_over", "up_wall")
    results = tmp_path / "results"
    results.mkdir()
    scal = rows("learned", "m/wide_10.pt", "wide", [ok, rolled]) + rows("learned", "m/wide_40.pt", "wide", [ok, ok])
    (results / "scalability.jsonl").write_text("".join(json.dumps(r) + "\n" for r in scal))
    (results / "baseline.jsonl").write_text(
        "".join(json.dumps(r) + "\n" for r in rows("dwa", "", "wide", [rolled, rolled])))
    (results / "dagger_round1.jsonl").write_text(
        "".join(json.dumps(r) + "\n" for r in rows("learned", "m/wide_dagger.pt", "wide", [ok, ok])))
    page = write_report([results], tmp_path / "results.md", tmp_path / "img", command="ditch-drake report results")
    text = page.read_text()
    # A file that is none of the paper's studies gets its own table, under its name.
    assert "## dagger_round1" in text and "| wide_dagger | wide | 2/2 | 100% |" in text
    # The models table says where each checkpoint came from, or that the file is no longer there.
    assert "| wide_10 | m/wide_10.pt |  | (file gone or changed since) |" in text
    assert "| wide_10 | wide | 1/2 | 50% | 9%-91% | 0 |" in text
    assert "rolled_over@up_wall 2" in text
    # 2 of 2 against 0 of 2 is higher, but not significantly (two-sided Boschloo p = 0.125).
    assert ("| every learned model beats move_base in its own environment: open field, against our DWA baseline "
            "(dwa: slopes from 45 deg lethal) | wide: wide_40 100% (p=0.12) vs 0%; 0 of 1 pairs higher with p < 0.05 "
            "| not significant |") in text
    assert "| success generally rises with demonstrations | wide 10: 50% -> 40: 100% | yes |" in text
    assert (tmp_path / "img" / "fig5_wide.png").exists() and (tmp_path / "img" / "fig5_baseline.png").exists()


def test_a_study_alone_plans_its_own_models_and_evaluations():
    config = load_experiment("experiments/paper.yaml")
    models, evaluations = plan(config, only_studies=["must_cross"])
    assert [m.name for m in models] == ["crater_40", "wide_40", "narrow_40", "sine_40"]
    assert {e.study for e in evaluations} == {"must_cross"} and len(evaluations) == 32
    models, evaluations = plan(config, only=["wide"], only_studies=["must_cross", "amalgam"])
    assert [m.name for m in models] == ["crater+narrow+sine_40", "wide_40"]
    assert Counter(e.study for e in evaluations) == {"must_cross": 8, "amalgam": 1}
