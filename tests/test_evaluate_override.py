"""`evaluate --override` over several environments: each runs its own model unless one is named."""

import json

import pytest

from ditch_drake.cli import main

SHORT = ["--task", "0", "--rollouts", "1", "--time-limit", "0.3", "--workers", "0"]


def _checkpoints(path) -> dict[str, str]:
    return {record["environment"]: record["checkpoint"] for record in map(json.loads, path.read_text().splitlines())}


@pytest.mark.parametrize("controller", [
    "!LearnedPolicyConfig {}",
    "!SharedControlControllerConfig {policy: {checkpoint: ''}}",
])
def test_each_environment_of_an_override_runs_its_own_model(tmp_path, controller):
    out = tmp_path / "results.jsonl"
    assert main(["evaluate", "--override", f"{{controller: {controller}}}", "--env", "crater", "--env", "wide",
                 *SHORT, "--out", str(out)]) == 0
    assert _checkpoints(out) == {"crater": "crater", "wide": "wide"}


def test_an_uncertainty_gate_with_the_default_gates_negative_thresholds_exits_2(tmp_path, capsys):
    out = tmp_path / "results.jsonl"
    override = "{controller: !SharedControlControllerConfig {policy: {checkpoint: ''}, gate: {signal: mean_softmax_entropy}}}"
    assert main(["evaluate", "--override", override, "--env", "wide", *SHORT, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "upper_threshold -6.826 with signal 'mean_softmax_entropy'" in err, err


def test_the_shared_controllers_default_policy_is_the_generalist_ensemble_everywhere(tmp_path):
    out = tmp_path / "results.jsonl"
    assert main(["evaluate", "--override", "{controller: !SharedControlControllerConfig {}}", "--env", "crater",
                 "--env", "wide", *SHORT, "--out", str(out)]) == 0
    assert _checkpoints(out) == {"crater": "generalist_k5", "wide": "generalist_k5"}


def test_a_named_checkpoint_runs_in_every_environment(tmp_path):
    out = tmp_path / "results.jsonl"
    assert main(["evaluate", "--override", "{controller: !LearnedPolicyConfig {checkpoint: wide_bc40}}",
                 "--env", "crater", "--env", "wide", *SHORT, "--out", str(out)]) == 0
    assert _checkpoints(out) == {"crater": "wide_bc40", "wide": "wide_bc40"}
