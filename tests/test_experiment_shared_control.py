"""The experiment's shared_control study: its plan (the ensembles, their files, the gates and their
random controls, the ensemble alone), the checks of its values, that the paper's other studies plan
what they did before, and a tiny run end to end on a two-member ensemble of untrained clones."""

from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.demos.store import DatasetStore
from ditch_drake.diagrams.rollout import LearnedPolicyConfig
from ditch_drake.evaluation.model_labels import controller_labels
from ditch_drake.evaluation.results import RolloutRecord, read_records
from ditch_drake.evaluation.runs import read_runs
from ditch_drake.learning.checkpoint import load_checkpoint, make_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.ensemble import EnsembleCheckpoint, load_ensemble, save_ensemble
from ditch_drake.learning.gate_calibration import load_signals
from ditch_drake.learning.model import FourInputClassifier
from ditch_drake.pipelines.experiment import (
    ModelSpec,
    evaluation_specs,
    gate_signals_path,
    load_experiment,
    model_path,
    plan,
    run_experiment,
    split_gating_paths,
    split_gating_specs,
)
from ditch_drake.world.environments import load_environments

PAPER = ["crater", "wide", "narrow", "sine"]
BUDGETS = [0.01, 0.02, 0.05, 0.1, 0.2]
PAPER_STUDIES = ["scalability", "generalization", "baseline", "amalgam", "must_cross"]
# What the paper's five studies planned before shared_control was added: its models in order.
PAPER_MODELS = ["crater_10", "crater_20", "crater_40", "wide_10", "wide_20", "wide_40", "narrow_10", "narrow_20",
                "narrow_40", "sine_10", "sine_20", "sine_40", "crater+narrow+sine_40"]

TINY = """
name: tiny
demos_dir: {root}/demos
models_dir: {root}/models
results_dir: {root}/results
report: {root}/docs/results.md
tasks: [1]
rollouts: 1
time_limit_s: 1.0
workers: 0
studies:
  shared_control: {{environments: [wide], demos: 2, ensemble: 2, budgets: [0.1], fallbacks: [expert],
                   calibration_rollouts: 1, seed: 5}}
"""


def test_the_paper_study_plans_a_k5_ensemble_per_ditch_its_gates_their_random_controls_and_the_ensemble_alone():
    config = load_experiment("experiments/paper.yaml")
    models, evaluations = plan(config, only_studies=["shared_control"])
    ensembles = [ModelSpec((env,), 40, 5) for env in PAPER]
    assert models == [m for env, ensemble in zip(PAPER, ensembles) for m in (
        ensemble, ModelSpec((env,), 40), *(ModelSpec((env,), 40, intervention_weight=w, round_labels=labels)
                                          for labels in ("executed", "expert") for w in (1.0, 3.0)))]
    assert [str(model_path(config, m)) for m in ensembles] == [f"models/paper/{env}_40_k5.pt" for env in PAPER]
    assert [str(gate_signals_path(config, m)) for m in ensembles] == [f"results/paper/gate/{env}_40_k5.npz"
                                                                       for env in PAPER]
    # Per ditch: the ensemble alone, per budget and fallback the gate and random handover, and
    # the aggregation round's clone before and after it (two labels x two weights), ungated.
    assert Counter(e.environment for e in evaluations) == dict.fromkeys(PAPER, 1 + 5 * 2 * 2 + 5)
    assert {e.study for e in evaluations} == {"shared_control"} and {e.seed for e in evaluations} == {300}
    for env, model in zip(PAPER, ensembles):
        here = [e for e in evaluations if e.environment == env]
        checkpoint = f"models/paper/{env}_40_k5.pt"
        *here, clone, uniform, weighted, expert_uniform, expert_weighted = here
        assert [(e.controller, e.config.checkpoint) for e in (clone, uniform, weighted, expert_uniform,
                                                              expert_weighted)] == [
            ("learned", f"models/paper/{env}_40{suffix}.pt")
            for suffix in ("", "_round_w1", "_round_w3", "_round_expert_w1", "_round_expert_w3")]
        assert {e.model for e in here} == {model}
        alone, *gated = here
        assert (alone.controller, alone.config) == ("learned", LearnedPolicyConfig(checkpoint=checkpoint))
        assert {e.controller for e in gated} == {"shared"}
        assert {e.config.policy.checkpoint for e in gated} == {checkpoint}
        gates = [e.config.gate for e in gated]
        assert [(g.budget, g.fallback, g.signal) for g in gates] == [
            (budget, fallback, signal) for budget in BUDGETS for fallback in ("expert", "mppi")
            for signal in ("angular_rate_spread", "random")]
        calibration = f"results/paper/gate/{env}_40_k5.npz"
        assert {(g.calibration, g.calm_steps) for g in gates if g.signal != "random"} == {(calibration, 5)}
        assert {(g.calibration, g.lower_threshold, g.calm_steps) for g in gates if g.signal == "random"} == {
            ("", 0.8, 5)}
    # --only wide keeps wide's ensemble, its clone before and after the round, and its 26 evaluations.
    models, evaluations = plan(config, only=["wide"], only_studies=["shared_control"])
    assert [m.name for m in models] == ["wide_40_k5", "wide_40", "wide_40_round_w1", "wide_40_round_w3",
                                        "wide_40_round_expert_w1", "wide_40_round_expert_w3"]
    assert len(evaluations) == 26


@pytest.mark.parametrize("fallback", ["expert", "mppi"])
def test_each_fallbacks_experiment_is_that_part_of_the_paper_study_on_the_same_ensembles(fallback):
    paper = load_experiment("experiments/paper.yaml")
    config = load_experiment(f"experiments/shared_control_{fallback}.yaml")
    models, evaluations = plan(config)
    # The same recipe, demonstrations and files: paper.yaml's study then reuses these ensembles.
    assert (config.training, config.seed, config.demos_dir, config.rollouts, config.time_limit_s) == (
        paper.training, paper.seed, paper.demos_dir, paper.rollouts, paper.time_limit_s)
    assert [str(model_path(config, m)) for m in models] == [f"models/paper/{env}_40_k5.pt" for env in PAPER]
    _, paper_evaluations = plan(paper, only_studies=["shared_control"])

    def fallback_part(evaluations):
        return [(e.environment, e.controller, e.seed, e.config.policy.checkpoint, replace(e.config.gate, calibration=""))
                if e.controller == "shared" else (e.environment, e.controller, e.seed, e.config)
                for e in evaluations if e.controller == "shared" and e.config.gate.fallback == fallback
                or e.controller == "learned" and e.config.checkpoint.endswith("_k5.pt")]

    assert fallback_part(evaluations) == fallback_part(paper_evaluations)
    assert len(evaluations) == 4 * (1 + 5 * 2)
    assert {e.config.gate.calibration for e in evaluations if e.controller == "shared"
            and e.config.gate.signal != "random"} == {
        f"results/shared_control_{fallback}/gate/{env}_40_k5.npz" for env in PAPER}


def test_the_paper_studies_plan_what_they_did_before_and_a_single_clone_keeps_its_name():
    config = load_experiment("experiments/paper.yaml")
    models, evaluations = plan(config, only_studies=PAPER_STUDIES)
    assert [m.name for m in models] == PAPER_MODELS and {m.ensemble for m in models} == {1}
    assert Counter(e.study for e in evaluations) == {"scalability": 12, "generalization": 12, "baseline": 4,
                                                     "amalgam": 1, "must_cross": 32}
    assert all(e.config is None and e.seed is None for e in evaluations)
    assert ModelSpec(("wide",), 40) == ModelSpec(("wide",), 40, 1) and ModelSpec(("wide",), 40).name == "wide_40"
    # A shared-control study of single clones gates the generalization study's own files, and
    # its aggregation round evaluates each clone once.
    single = replace(config.studies.shared_control, ensemble=1, signal="mean_softmax_entropy")
    models, evaluations = plan(replace(config, studies=replace(config.studies, shared_control=single)),
                               only_studies=["shared_control"])
    assert [str(model_path(config, m)) for m in models if m.intervention_weight is None] == [
        f"models/paper/{env}_40.pt" for env in PAPER]
    assert Counter(e.environment for e in evaluations if e.controller == "learned") == dict.fromkeys(PAPER, 5)


@pytest.mark.parametrize("values, message", [
    ("budgets: [0.05, 1.5]", r"studies\.shared_control\.budgets=\[0\.05, 1\.5\]"),
    ("budgets: []", r"studies\.shared_control\.budgets=\[\]"),
    ("fallbacks: [expert, human]", r"studies\.shared_control\.fallbacks=\['expert', 'human'\]"),
    ("fallbacks: [teleop]", r"studies\.shared_control\.fallbacks=\['teleop'\].*'expert', 'mppi'"),
    ("environments: [wide, moon]", r"unknown environments \['moon'\] \(studies\.shared_control\.environments\)"),
    ("ensemble: 1", r"studies\.shared_control\.ensemble=1: the signal 'angular_rate_spread'.*K >= 2"),
    ("signal: random", r"studies\.shared_control\.signal='random'"),
    ("seed: 5", r"studies\.shared_control\.seed=5: its seeds 5-5 overlap the calibration's 0-9"),
    ("calibration_rollouts: 0", r"studies\.shared_control\.calibration_rollouts=0"),
    ("budgets: [0.05], random_lower_threshold: 1.5", r"studies\.shared_control: random handover at budget 0\.05.*lower_threshold"),
    ("aggregation: {signal: angular_rate_spread}",
     r"aggregation\.signal='angular_rate_spread': expected one a single clone gives"),
    ("aggregation: {budget: 0}", r"aggregation\.budget=0\.0: expected a share of control steps in \(0, 1\)"),
    ("aggregation: {fallback: teleop}", r"aggregation\.fallback='teleop'"),
    ("aggregation: {rollouts: 0}", r"aggregation\.rollouts=0: expected an integer >= 1"),
    ("aggregation: {intervention_weights: [1, -2]}", r"aggregation\.intervention_weights=\[1\.0, -2\.0\]: expected positive"),
    ("aggregation: {intervention_weights: []}", r"aggregation\.intervention_weights=\[\]"),
    ("aggregation: {seed: 295}", r"aggregation\.seed=295: its seeds 295-314 overlap the study's test seeds 300-300"),
    ("aggregation: {seed: 9}", r"aggregation\.seed=9: its seeds 9-28 overlap the calibration's 0-9"),
    ("aggregation: {labels: [executed, person]}", r"aggregation\.labels=\['executed', 'person'\]: expected some of"),
    ("aggregation: {labels: [expert], fallback: mppi}", r"aggregation\.labels=\['expert'\] with fallback 'mppi'"),
    ("aggregation: {shared_steps: [supervised]}", r"aggregation\.shared_steps=\['supervised'\]: expected some of"),
    ("aggregation: {shared_steps: []}", r"aggregation\.shared_steps=\[\]: expected some of"),
    ("split: {calibration_split: test}", r"split\.calibration_split='test': the gate's thresholds are a choice"),
    ("split: {split: moon}", r"studies\.shared_control\.split: unknown split 'moon'"),
    ("split: {geometries: 0}", r"studies\.shared_control\.split: geometries=0 is out of range for split 'test'"),
    ("split: {calibration_geometries: 51}", r"geometries=51 is out of range for split 'val'"),
    ("split: {seed: -1}", r"studies\.shared_control\.split: .*-1"),
    ("split: {checkpoint: wide}", r"split\.checkpoint='wide': a single clone, and the signal 'angular_rate_spread'"),
    ("split: {checkpoint: nowhere.pt}", r"studies\.shared_control\.split: .*nowhere\.pt"),
    ("split: {budgets: [0.02, 1]}", r"split\.budgets=\[0\.02, 1\.0\]: expected shares of control steps in \(0, 1\)"),
    ("split: {fallbacks: [teleop]}", r"split\.fallbacks=\['teleop'\]: expected some of \['expert', 'mppi'\]"),
    ("split: {signal: random}", r"split\.signal='random': expected one of"),
    ("split: {checkpoint: wide, signal: vote_entropy}", r"split\.checkpoint='wide': a single clone, and the signal 'vote_entropy'"),
    ("signal: seconds_without_progress", r"studies\.shared_control\.signal='seconds_without_progress': expected one of"),
    ("progress_limit_s: 0", r"studies\.shared_control\.progress_limit_s=0\.0: .*expected a number of seconds > 0"),
    ("regress_limit_m: -6", r"studies\.shared_control\.regress_limit_m=-6\.0: .*expected a number of metres > 0"),
    ("regress_limit_m: .nan", r"studies\.shared_control\.regress_limit_m=nan: .*expected a number of metres > 0"),
])
def test_bad_study_values_are_refused_naming_the_key(tmp_path, values, message):
    path = tmp_path / "bad.yaml"
    path.write_text(f"rollouts: 1\nstudies:\n  shared_control: {{{values}}}\n")
    with pytest.raises(ConfigError, match=message):
        load_experiment(path)


def test_the_watchdogs_file_gates_the_paper_ensembles_on_the_tip_risk_and_random_handover_both_beside_the_watchdogs():
    paper = load_experiment("experiments/paper.yaml")
    config = load_experiment("experiments/shared_control_watchdogs.yaml")
    models, evaluations = plan(config)
    assert (config.training, config.seed, config.demos_dir, config.rollouts, config.time_limit_s) == (
        paper.training, paper.seed, paper.demos_dir, paper.rollouts, paper.time_limit_s)
    assert [str(model_path(config, m)) for m in models] == [f"models/paper/{env}_40_k5.pt" for env in PAPER]
    # The risk signal's thresholds come from a recording with the tip risk in it.
    assert [str(gate_signals_path(config, m)) for m in models] == [
        f"results/shared_control_watchdogs/gate/{env}_40_k5_risk.npz" for env in PAPER]
    assert len(evaluations) == 4 * (1 + 2 * 2) and {e.seed for e in evaluations} == {300}
    gates = [e.config.gate for e in evaluations if e.controller == "shared"]
    assert [(g.signal, g.fallback) for g in gates[:4]] == [
        ("tip_risk_ahead", "expert"), ("random", "expert"), ("tip_risk_ahead", "mppi"), ("random", "mppi")]
    # The control keeps the watchdogs too: what differs from the gate is only when it hands over.
    assert {(g.budget, g.progress_limit_s, g.regress_limit_m) for g in gates} == {(0.02, 20.0, 6.0)}
    # Without watchdogs, the paper's study gates as before: no limits written into its records.
    _, paper_evaluations = plan(paper, only_studies=["shared_control"])
    assert all(e.config.gate.watchdog_limits() == {} for e in paper_evaluations if e.controller == "shared")


def test_the_command_exits_2_on_a_bad_budget(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("studies:\n  shared_control: {budgets: [0.1, 0]}\n")
    assert main(["experiment", str(path), "--study", "shared_control", "--stage", "report"]) == 2
    assert "studies.shared_control.budgets=[0.1, 0.0]: expected shares of control steps in (0, 1)" in capsys.readouterr().err


def _ensemble(path: Path) -> Path:
    """Two untrained clones as an ensemble file: the disagreement signals are defined."""
    def member(seed: int):
        torch.manual_seed(seed)
        return make_checkpoint(FourInputClassifier().eval(), metrics={"best": {}},
                               training={"train_demo_ids": [0], "val_demo_ids": [1], "train_config": {"device": "cpu"}})

    return save_ensemble(EnsembleCheckpoint([member(0), member(1)]), path)


def test_a_tiny_study_calibrates_then_evaluates_and_reports_distinct_rows_and_a_rerun_redoes_nothing(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.format(root=tmp_path))
    config = load_experiment(path)
    models, evaluations = plan(config)
    assert [m.name for m in models] == ["wide_2_k2"] and len(evaluations) == 3
    # No ensemble yet: the evaluation has nothing to run (and no signals file to read).
    assert evaluation_specs(config, evaluations[1]) == []
    ensemble = _ensemble(tmp_path / "models" / "wide_2_k2.pt")
    assert evaluation_specs(config, evaluations[1]) == []  # Trained, not yet calibrated.
    ensemble_time = ensemble.stat().st_mtime_ns

    run_experiment(config, stages=("train", "evaluate", "report"), progress=False)
    assert ensemble.stat().st_mtime_ns == ensemble_time  # A finished ensemble is kept.
    signals = tmp_path / "results" / "gate" / "wide_2_k2.npz"
    assert signals.is_file() and (tmp_path / "results" / "gate" / "wide_2_k2.auc.json").is_file()
    assert not (tmp_path / "results" / "gate" / "wide_2_k2.npz.parts").exists()
    records = read_records(tmp_path / "results" / "shared_control.jsonl")[0]
    assert [(r.controller, r.environment, r.task, r.seed, r.checkpoint) for r in records] == [
        (controller, "wide", 1, 5, str(ensemble)) for controller in ("learned", "shared", "shared")]
    assert all(r.status != "error" for r in records), [r.error for r in records]
    gates = [yaml.safe_load(r.controller_config)["gate"] for r in records[1:]]
    assert [(g["signal"], g["budget"], g["fallback"]) for g in gates] == [
        ("angular_rate_spread", 0.1, "expert"), ("random", 0.1, "expert")]
    assert gates[0]["calibration"] == str(signals) and gates[1]["lower_threshold"] == 0.8

    page = (tmp_path / "docs" / "results.md").read_text()
    study = page.split("## shared_control")[1].split("### Shared control")
    rows = [line.split(" | ")[0].lstrip("| ") for line in study[0].splitlines() if "| wide |" in line]
    assert rows == ["wide_2_k2",
                    "wide_2_k2 (gate angular_rate_spread, budget 0.1, fallback expert; privileged: analytic terrain)",
                    "wide_2_k2 (gate random, budget 0.1, fallback expert; privileged: analytic terrain)"]
    shared = [line.split(" | ")[0].lstrip("| ") for line in study[1].splitlines() if "| wide |" in line]
    assert shared == rows[1:]

    signals_time = signals.stat().st_mtime_ns
    run_experiment(config, stages=("train", "evaluate"), progress=False)
    assert signals.stat().st_mtime_ns == signals_time
    assert len(read_records(tmp_path / "results" / "shared_control.jsonl")[0]) == 3
    assert len(read_runs(tmp_path / "results")) == 2


def test_a_tiny_study_on_the_tip_risk_records_the_risk_then_gates_beside_its_watchdogs(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.format(root=tmp_path).replace(
        "seed: 5}", "seed: 5, signal: tip_risk_ahead, progress_limit_s: 20, regress_limit_m: 6}"))
    config = load_experiment(path)
    _ensemble(tmp_path / "models" / "wide_2_k2.pt")
    run_experiment(config, stages=("evaluate",), progress=False)
    signals = tmp_path / "results" / "gate" / "wide_2_k2_risk.npz"
    assert "tip_risk_ahead" in load_signals(signals)["signals"]
    records = read_records(tmp_path / "results" / "shared_control.jsonl")[0]
    assert all(r.status != "error" for r in records), [r.error for r in records]
    gates = [yaml.safe_load(r.controller_config)["gate"] for r in records[1:]]
    assert [(g["signal"], g["progress_limit_s"], g["regress_limit_m"]) for g in gates] == [
        ("tip_risk_ahead", 20.0, 6.0), ("random", 20.0, 6.0)]
    assert gates[0]["calibration"] == str(signals)


def test_the_train_stage_trains_the_ensemble_that_train_ensemble_does(tmp_path, random_demonstration):
    store = DatasetStore.create(tmp_path / "demos" / "wide")
    for index, steps in enumerate((9, 6, 11, 5, 8)):
        store.append(random_demonstration(index, steps))
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.format(root=tmp_path).replace("demos: 2,", "demos: 4,")
                    + "training: {epochs: 1, patience: 1, batches_per_epoch: 1, synthetic_fraction: 0.5}\n")
    run_experiment(load_experiment(path), stages=("train",), progress=False)
    by_command = tmp_path / "by_command.pt"
    assert main(["train", "--data", str(tmp_path / "demos" / "wide"), "--max-demos", "4", "--seed", "0",
                 "--ensemble", "2", "--epochs", "1", "--patience", "1", "--batches-per-epoch", "1",
                 "--synthetic-fraction", "0.5", "--balancing", "smote", "--out", str(by_command)]) == 0
    staged, commanded = (load_ensemble(tmp_path / "models" / "wide_4_k2.pt"), load_ensemble(by_command))
    assert staged.bootstrap == commanded.bootstrap and len(staged.bootstrap["demonstrations"]) == 4
    for ours, theirs in zip(staged.members, commanded.members, strict=True):
        assert ours.training["train_config"] == theirs.training["train_config"]
        assert all(torch.equal(ours.state_dict[key], theirs.state_dict[key]) for key in theirs.state_dict)


def test_the_aggregation_round_gates_the_clone_records_its_handovers_and_retrains_as_the_commands_do(
        tmp_path, random_demonstration):
    store = DatasetStore.create(tmp_path / "demos" / "wide")
    for index, steps in enumerate((9, 6, 11, 5, 8, 7)):
        store.append(random_demonstration(index, steps))
    path = tmp_path / "round.yaml"
    path.write_text(TINY.format(root=tmp_path).replace(
        "demos: 2, ensemble: 2,", "demos: 6, ensemble: 1, signal: mean_softmax_entropy,").replace(
        "seed: 5}", "seed: 5, aggregation: {signal: tip_risk_ahead, budget: 0.5, rollouts: 1, seed: 20, "
                    "intervention_weights: [3], labels: [executed, expert], shared_steps: [all, interventions]}}")
                    + "training: {epochs: 1, patience: 1, batches_per_epoch: 1, synthetic_fraction: 0.5}\n")
    config = load_experiment(path)
    models, evaluations = plan(config)
    suffixes = ("", "_round_w3", "_round_interventions_w3", "_round_expert_w3", "_round_expert_interventions_w3")
    assert [m.name for m in models] == [f"wide_6{suffix}" for suffix in suffixes]
    assert [e.config.checkpoint for e in evaluations if e.controller == "learned"] == [
        str(tmp_path / "models" / f"wide_6{suffix}.pt") for suffix in suffixes]
    # The clone is the shipped wide model, so that the gated episode crosses in a few seconds. Its
    # calibration is one second on flat ground, so only a large budget gives a finite threshold.
    clone = tmp_path / "models" / "wide_6.pt"
    clone.parent.mkdir()
    clone.write_bytes(resolve_checkpoint_path("wide").read_bytes())

    run_experiment(config, stages=("train",), progress=False)
    signals = tmp_path / "results" / "gate" / "wide_6_risk.npz"
    assert "tip_risk_ahead" in load_signals(signals)["signals"]
    handovers = DatasetStore.open(tmp_path / "demos" / "handovers" / "wide_6")
    (episode,) = handovers.episodes()
    gate = episode.metadata["shared_gate"]
    assert (gate["signal"], gate["budget"], gate["calibration"], gate["fallback"]) == (
        "tip_risk_ahead", 0.5, str(signals), "expert")
    assert episode.metadata["learner"] == str(clone) and episode.metadata["expert_style"]["reaction_delay_steps"] == 0
    flags = np.asarray(handovers.read(episode, ["intervention"])["intervention"])
    assert 0 < flags.sum() == episode.metadata["intervened_steps"] < len(flags)
    # The expert-labelled copy: the same episode step for step, the expert's label at each.
    relabelled = DatasetStore.open(tmp_path / "demos" / "handovers" / "wide_6_expert")
    (copy,) = relabelled.episodes()
    assert copy.metadata["shared_labels"] == "expert" and copy.steps == episode.steps
    copied = relabelled.read(copy, ["intervention", "imu_stack", "label"])
    executed = handovers.read(episode, ["imu_stack", "label"])
    assert np.array_equal(copied["intervention"], flags) and np.array_equal(copied["imu_stack"], executed["imu_stack"])
    assert np.array_equal(copied["label"][flags], executed["label"][flags])  # Where the expert drove, its own.
    assert (tmp_path / "models" / "wide_6_round_expert_w3.pt").is_file()

    by_command = tmp_path / "by_command.pt"
    assert main(["train", "--data", str(tmp_path / "demos" / "wide"), "--data", str(handovers.root),
                 "--intervention-weight", "3", "--seed", "0", "--epochs", "1", "--patience", "1",
                 "--batches-per-epoch", "1", "--synthetic-fraction", "0.5", "--balancing", "smote",
                 "--out", str(by_command)]) == 0
    staged, commanded = load_checkpoint(tmp_path / "models" / "wide_6_round_w3.pt"), load_checkpoint(by_command)
    assert staged.training["train_config"]["intervention_weight"] == 3.0
    assert 6 in staged.training["train_demo_ids"] and staged.training["intervention_train_samples"] > 0
    assert staged.training["train_config"] == commanded.training["train_config"]
    # The clone's six demonstrations and the round's episode, its interventions weighed as the command weighs them.
    assert sorted(staged.training["train_demo_ids"] + staged.training["val_demo_ids"]) == list(range(7))
    assert staged.training["intervention_train_samples"] == commanded.training["intervention_train_samples"]
    assert all(torch.equal(staged.state_dict[key], commanded.state_dict[key]) for key in commanded.state_dict)

    # Only the expert's steps of the round's episode (HG-DAgger), as `train --shared-steps interventions`.
    assert main(["train", "--data", str(tmp_path / "demos" / "wide"), "--data", str(handovers.root),
                 "--intervention-weight", "3", "--shared-steps", "interventions", "--seed", "0", "--epochs", "1",
                 "--patience", "1", "--batches-per-epoch", "1", "--synthetic-fraction", "0.5", "--balancing", "smote",
                 "--out", str(by_command)]) == 0
    staged = load_checkpoint(tmp_path / "models" / "wide_6_round_interventions_w3.pt")
    commanded = load_checkpoint(by_command)
    assert staged.training["train_config"]["shared_steps"] == "interventions"
    assert staged.training["train_config"] == commanded.training["train_config"]
    assert staged.training["intervention_train_samples"] == commanded.training["intervention_train_samples"] > 0
    every_step = load_checkpoint(tmp_path / "models" / "wide_6_round_w3.pt").training
    assert (staged.training["num_train_samples"] + staged.training["num_val_samples"]
            < every_step["num_train_samples"] + every_step["num_val_samples"])
    assert all(torch.equal(staged.state_dict[key], commanded.state_dict[key]) for key in commanded.state_dict)


def test_a_gated_records_label_names_its_gate_whatever_the_yaml_style_and_others_keep_theirs():
    def record(controller: str, config: str) -> RolloutRecord:
        return RolloutRecord(
            key=controller + config, controller=controller, checkpoint="m/wide_40_k5.pt", environment="wide", task=0,
            seed=0, time_limit_s=120.0, goal_radius_m=1.5, checkpoint_sha256="", failure_region="", status="reached_goal",
            success=True, time_s=1.0,
            path_length_m=1.0, peak_abs_roll_deg=0.0, peak_abs_pitch_deg=0.0, peak_tilt_deg=0.0,
            min_stability_margin_deg=0.0, final_x_m=0.0, final_y_m=0.0, wall_s=1.0, controller_config=config)

    records = [record("learned", "checkpoint: m/wide_40_k5.pt\n"),
               record("shared", "policy: {checkpoint: x}\ngate: {signal: random, upper_threshold: 0.99, budget: 0.02, "
                                "fallback: mppi}\nexpert: {}\n"),
               record("shared", "policy: {checkpoint: x}\ngate:\n  signal: mean_softmax_entropy\n  "
                                "upper_threshold: 2.55\n  fallback: expert\nmppi: {}\n")]
    assert [controller_labels(records)(r) for r in records] == [
        "wide_40_k5", "wide_40_k5 (gate random, budget 0.02, fallback mppi)",
        "wide_40_k5 (gate mean_softmax_entropy, fallback expert)"]


def test_the_paper_file_gates_the_generalist_ensemble_on_the_test_split_calibrated_on_val():
    part = load_experiment("experiments/paper.yaml").studies.shared_control.split
    assert (part.checkpoint, part.calibration_split, part.split, part.seed, part.geometries) == (
        "generalist_k5", "val", "test", 0, None)
    assert (part.budgets, part.fallbacks, part.signal) == ([0.01, 0.02, 0.05, 0.1, 0.2], ["expert", "mppi"], "tip_risk_ahead")


SPLIT_PART = """
name: tiny split
results_dir: {root}/results
report: {root}/docs/results.md
time_limit_s: 1.0
workers: 0
studies:
  shared_control: {{environments: [wide], demos: 2, ensemble: 2, budgets: [0.1], fallbacks: [expert],
                   split: {{checkpoint: generalist_k5, calibration_geometries: 1, geometries: 1, budgets: [0.1],
                           fallbacks: [expert], signal: tip_risk_ahead}}}}
"""


def test_the_split_part_records_its_signals_on_val_then_the_policy_and_its_gates_on_test(tmp_path):
    path = tmp_path / "split.yaml"
    path.write_text(SPLIT_PART.format(root=tmp_path))
    config = load_experiment(path)
    part = config.studies.shared_control.split
    run_experiment(config, stages=("evaluate", "report"), progress=False)  # The wide ensemble is untrained: skipped.
    signals, results = split_gating_paths(config, part)
    assert (signals, results) == (tmp_path / "results" / "gate" / "generalist_k5_val_risk.npz",
                                  tmp_path / "results" / "shared_control_test.jsonl")
    assert list(load_environments(tmp_path / "results" / "gate" / "generalist_k5_val_risk.ditches.yaml")) == [
        "ditch_1000"]
    recorded = load_signals(signals)
    assert recorded["episode_seed"].size == 3 and "tip_risk_ahead" in recorded["signals"]  # ditch_1000's tasks.
    records = read_records(results)[0]
    # Per task of the first test ditch: the policy alone, the gate and random handover.
    assert Counter((r.controller, r.environment, r.seed, r.checkpoint) for r in records) == {
        ("learned", "ditch_2000", 0, "generalist_k5"): 3, ("shared", "ditch_2000", 0, "generalist_k5"): 6}
    assert all(r.status != "error" for r in records), [r.error for r in records]
    assert {r.environments_file for r in records} == {str(tmp_path / "results" / "shared_control_test.ditches.yaml")}
    gates = [yaml.safe_load(r.controller_config)["gate"] for r in records if r.controller == "shared"]
    assert Counter((g["signal"], g["budget"], g["fallback"], g.get("calibration")) for g in gates) == {
        ("tip_risk_ahead", 0.1, "expert", str(signals)): 3, ("random", 0.1, "expert", None): 3}
    assert len(split_gating_specs(config, part)) == 9
    page = (tmp_path / "docs" / "results.md").read_text().split("## shared_control_test")[1]
    assert "| generalist_k5 (perceived side) | 1 generated ditch | 0/3 |" in page  # One row per model.
    # Run again: the signals file and every rollout are kept.
    signals_time = signals.stat().st_mtime_ns
    run_experiment(config, stages=("evaluate",), progress=False)
    assert signals.stat().st_mtime_ns == signals_time and len(read_records(results)[0]) == 9
