"""Which signal foresees a rollover, and the gate's thresholds from a budget: the AUC and its
episode bootstrap on synthetic cases, the labels of the steps before a rollover, a budget's
thresholds from a signals file (and in a batch's records), and `ditch-drake gate-signals` on a
short rollout."""

import dataclasses
import math

import numpy as np
import pytest
import yaml

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig
from ditch_drake.evaluation.batch import make_specs
from ditch_drake.learning.checkpoint import checkpoint_digest
from ditch_drake.learning.gate_calibration import (
    FALLBACK,
    POLICY,
    bootstrap_auc_interval,
    budget_thresholds,
    calibration_values,
    failure_labels,
    gate_step,
    load_signals,
    quantile_thresholds,
    replay_fallback_share,
    roc_auc,
    save_signals,
    signal_aucs,
)
from ditch_drake.systems.shared_control import SharedControl, SharedControlConfig
from ditch_drake.world.environments import load_environments


def _signals_file(path, values, checkpoint="wide", status=("rolled_over", "reached_goal")):
    """Two episodes of len(values) / 2 steps 0.1 s apart, each ending at its last step."""
    half = len(values) // 2
    times = np.tile(np.arange(half) * 0.1, 2)
    save_signals(path, checkpoint, checkpoint_digest(checkpoint), {"mean_softmax_entropy": values},
                 {"time_s": times, "episode": np.repeat([0, 1], half)},
                 {"episode_environment": ["wide", "wide"], "episode_task": [1, 1], "episode_seed": [0, 1],
                  "episode_status": list(status), "episode_end_time_s": [times[half - 1]] * 2})
    return path


def test_the_auc_of_a_perfect_a_reversed_and_a_constant_predictor():
    labels = np.array([0, 0, 0, 1, 1, 0, 1], dtype=bool)
    assert roc_auc(labels.astype(float), labels) == 1.0
    assert roc_auc(-labels.astype(float), labels) == 0.0
    assert roc_auc(np.full(labels.size, 2.3), labels) == 0.5
    assert roc_auc([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1]) == 0.75  # 3 of the 4 pairs ranked right.
    assert math.isnan(roc_auc([0.1, 0.2], [0, 0]))  # No positive step: no AUC.


def test_the_bootstrap_resamples_whole_episodes_with_a_seed():
    rng = np.random.default_rng(0)
    episode = np.repeat(np.arange(10), 20)
    labels = (episode % 2 == 0) & (np.tile(np.arange(20), 10) >= 15)
    scores = labels + rng.normal(0.0, 0.6, labels.size)
    low, high, used = bootstrap_auc_interval(scores, labels, episode, seed=3, resamples=200)
    assert low < roc_auc(scores, labels) < high and 0.5 < low and high <= 1.0 and 0 < used <= 200
    assert bootstrap_auc_interval(scores, labels, episode, seed=3, resamples=200) == (low, high, used)
    assert bootstrap_auc_interval(labels.astype(float), labels, episode, seed=0, resamples=50)[:2] == (1.0, 1.0)
    nan_low, nan_high, none = bootstrap_auc_interval(scores, np.zeros(labels.size, bool), episode, resamples=5)
    assert math.isnan(nan_low) and math.isnan(nan_high) and none == 0


def test_steps_within_two_seconds_before_a_rollover_are_labelled():
    time_s = np.array([0.0, 2.9, 3.0, 4.5, 5.0, 0.0, 4.9])
    episode = np.array([0, 0, 0, 0, 0, 1, 1])
    labels = failure_labels(time_s, episode, end_time_s=[5.0, 5.0], status=["rolled_over", "timeout"])
    assert labels.tolist() == [False, False, True, True, True, False, False]
    assert failure_labels(time_s, episode, [5.0, 5.0], ["rolled_over", "timeout"], horizon_s=0.5).tolist() == [
        False, False, False, True, True, False, False]


def test_a_budget_hands_over_its_share_of_the_recorded_steps_hysteresis_included(tmp_path):
    values = np.random.default_rng(1).gamma(4.0, 0.3, 2000)
    path = _signals_file(tmp_path / "signals.npz", values)
    episodes = [values[:1000], values[1000:]]
    assert [len(e) for e in calibration_values(path, "mean_softmax_entropy")] == [1000, 1000]
    for budget in (0.01, 0.05, 0.2):
        gate = SharedControlConfig(signal="mean_softmax_entropy", budget=budget, calibration=str(path)).resolved()
        upper, lower, calm_steps = gate.upper_threshold, gate.lower_threshold, gate.calm_steps
        # Replayed over the recorded episodes (their first warmup_steps ignored, as the block
        # does), the gate hands over the budget's share of the steps, to within one step of
        # 2000 (the signal is continuous).
        replayed = replay_fallback_share(episodes, upper, lower, calm_steps, gate.warmup_steps)
        assert replayed == pytest.approx(budget, abs=1e-3) and replayed <= budget
        # Both thresholds are quantiles at one share s: the upper one the (1 - s), the lower the (1 - 2 s).
        share = np.mean(values > upper)
        assert np.mean(values > lower) == pytest.approx(2 * share, abs=1e-3)
        # The calm steps hold each handover: s is below the budget, and the quantiles at the
        # budget itself (the rule without the hysteresis) would hand over more than the budget.
        assert share < budget
        assert replay_fallback_share(episodes, *quantile_thresholds(values, budget), calm_steps,
                                     gate.warmup_steps) > budget
        assert SharedControl(gate).config.upper_threshold == upper
    # Without hysteresis and with the band closed, the quantile itself: s is the budget.
    upper, lower = budget_thresholds(episodes, 0.05, calm_steps=1)
    assert np.mean(values > upper) <= 0.05 and replay_fallback_share(episodes, upper, lower, 1) <= 0.05
    assert quantile_thresholds(values, 0.6)[1] == values.min()  # 1 - 2 s < 0: the smallest value.
    for bad in (0, 1, -0.1, 1.5, True):
        with pytest.raises(ConfigError, match=f"budget {bad!r}: expected a share of control steps in"):
            budget_thresholds(values, bad)


def test_the_replay_is_the_gates_hysteresis():
    # Over 0.5 hands over; three steps below 0.2 in a row hand back.
    sequence = [0.1, 0.6, 0.1, 0.1, 0.3, 0.1, 0.1, 0.1, 0.4, 0.9, 0.0]
    drivers, driver, calm = [], POLICY, 0
    for value in sequence:
        driver, calm, _ = gate_step(driver, calm, value, 0.5, 0.2, 3)
        drivers.append(driver)
    assert drivers == [POLICY, FALLBACK, FALLBACK, FALLBACK, FALLBACK, FALLBACK, FALLBACK, POLICY, POLICY,
                       FALLBACK, FALLBACK]
    assert replay_fallback_share([sequence], 0.5, 0.2, 3) == pytest.approx(8 / 11)
    # Each episode starts with the policy driving.
    assert replay_fallback_share([sequence[:3], sequence[:3]], 0.5, 0.2, 3) == pytest.approx(4 / 6)


def test_the_auc_rows_of_a_signals_file(tmp_path):
    values = np.concatenate([np.linspace(0.5, 2.0, 50), np.full(50, 1.0)])  # Rising toward the rollover.
    signals = load_signals(_signals_file(tmp_path / "s.npz", values))
    (row,) = signal_aucs(signals, horizon_s=2.0, seed=0, resamples=50)
    assert (row["signal"], row["positive_steps"], row["steps"], row["rolled_over_episodes"]) == (
        "mean_softmax_entropy", 21, 100, 1)  # 2.9 s .. 4.9 s of the rolled-over episode.
    assert row["auc"] == 1.0


def test_a_budgeted_shared_config_records_the_thresholds_it_ran_with(tmp_path):
    values = np.random.default_rng(2).uniform(0.0, 2.8, 400)
    path = _signals_file(tmp_path / "wide.npz", values)
    config = dataclasses.replace(SharedControlControllerConfig().with_checkpoint("wide"), gate=SharedControlConfig(
        signal="mean_softmax_entropy", budget=0.05, calibration=str(path)))
    (spec,) = make_specs(config, "", "wide", [1], rollouts=1, time_limit_s=2.0)
    gate = yaml.safe_load(spec.controller_config)["gate"]
    upper, lower = budget_thresholds([values[:200], values[200:]], 0.05, SharedControlConfig().calm_steps)
    assert (gate["upper_threshold"], gate["lower_threshold"]) == (pytest.approx(upper), pytest.approx(lower))
    assert upper > np.quantile(values, 0.95)  # The hysteresis counted in: fewer handovers than the quantile's.
    assert (gate["budget"], gate["calibration"]) == (0.05, str(path))
    other = config.with_checkpoint("narrow")  # Another policy's signal says nothing of this one's.
    with pytest.raises(ConfigError, match="gate.calibration .* recorded with checkpoint digest"):
        make_specs(other, "", "narrow", [1], rollouts=1, time_limit_s=2.0)


def test_a_risk_gate_takes_its_thresholds_only_from_a_file_of_its_own_arc(tmp_path):
    from ditch_drake.systems.tip_risk import TipRiskConfig

    values = -np.random.default_rng(5).uniform(3.0, 60.0, 400)
    half = len(values) // 2
    times = np.tile(np.arange(half) * 0.1, 2)
    def risk_file(name, horizon_s):
        return save_signals(tmp_path / name, "wide", checkpoint_digest("wide"), {"tip_risk_ahead": values},
                            {"time_s": times, "episode": np.repeat([0, 1], half)},
                            {"episode_environment": ["wide", "wide"], "episode_task": [1, 1], "episode_seed": [0, 1],
                             "episode_status": ["rolled_over", "reached_goal"],
                             "episode_end_time_s": [times[half - 1]] * 2}, tip_risk_horizon_s=horizon_s)
    gate = SharedControlConfig(signal="tip_risk_ahead", budget=0.05, calibration=str(risk_file("h3.npz", 3.0)))
    config = dataclasses.replace(SharedControlControllerConfig().with_checkpoint("wide"), gate=gate)
    assert load_signals(gate.calibration)["tip_risk_horizon_s"] == 3.0
    with pytest.raises(ConfigError, match="recorded on arcs of 3 s, the gate's policy.tip_risk.horizon_s is 2"):
        config.resolved()
    held = dataclasses.replace(config, policy=dataclasses.replace(config.policy, tip_risk=TipRiskConfig(horizon_s=3.0)))
    assert held.resolved().gate.upper_threshold < 0
    # A file that names no horizon was recorded at the default.
    unnamed = dataclasses.replace(config, gate=dataclasses.replace(gate, calibration=str(risk_file("old.npz", None))))
    assert "tip_risk_horizon_s" not in load_signals(unnamed.gate.calibration)
    assert unnamed.resolved().gate.upper_threshold < 0
    with pytest.raises(ConfigError, match="recorded on arcs of 2 s"):
        dataclasses.replace(unnamed, policy=held.policy).resolved()


def test_gate_signals_records_every_step_of_a_short_rollout(tmp_path, capsys):
    out = tmp_path / "signals.npz"
    argv = ["gate-signals", "--workers", "0", "--checkpoint", "wide_bc40", "--env", "wide", "--task", "1",
            "--rollouts", "1", "--seed", "4", "--time-limit", "1", "--out", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "mean_softmax_entropy" in printed and "auc" in printed
    signals = load_signals(out)
    assert signals["signals"] == ["mean_softmax_entropy", "command_reversals", "seconds_without_progress", "metres_regressed"]
    assert signals["checkpoint"] == "wide_bc40"
    assert signals["checkpoint_sha256"] == checkpoint_digest("wide_bc40")
    np.testing.assert_allclose(signals["time_s"], 0.003 + 0.1 * np.arange(10), atol=1e-9)
    assert signals["episode"].tolist() == [0] * 10
    assert signals["mean_softmax_entropy"].shape == (10,)
    assert np.all((signals["mean_softmax_entropy"] > 0) & (signals["mean_softmax_entropy"] < np.log(17)))
    assert (signals["episode_status"].tolist(), signals["episode_end_time_s"].tolist(),
            signals["episode_seed"].tolist()) == (["timeout"], [1.0], [4])
    assert (tmp_path / "signals.auc.json").is_file()
    # It never overwrites a recording.
    assert main(argv) == 2
    assert "exists" in capsys.readouterr().err


def test_gate_signals_on_a_split_records_on_its_ditches_written_beside_the_file(tmp_path, capsys):
    out = tmp_path / "val.npz"
    argv = ["gate-signals", "--workers", "0", "--checkpoint", "wide_bc40", "--split", "val", "--geometries", "1",
            "--task", "1", "--rollouts", "1", "--time-limit", "1", "--out", str(out)]
    assert main(argv) == 0
    signals = load_signals(out)
    assert signals["episode_environment"].tolist() == ["ditch_1000"] and signals["episode_task"].tolist() == [1]
    assert list(load_environments(tmp_path / "val.ditches.yaml")) == ["ditch_1000"]


@pytest.mark.parametrize("options, message", [
    (["--split", "test"], "--split 'test': held out for reporting"),
    (["--split", "val", "--environments", "x.yaml"], "--split val with --environments x.yaml"),
    (["--geometries", "2"], "--geometries without --split"),
])
def test_gate_signals_refuses_a_held_out_split_or_split_options_alone(tmp_path, capsys, options, message):
    out = tmp_path / "s.npz"
    assert main(["gate-signals", "--checkpoint", "wide_bc40", *options, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert not out.exists() and not (tmp_path / "s.ditches.yaml").exists()


@pytest.mark.parametrize("options, message", [
    (["--rollouts", "0"], "--rollouts"),
    (["--task", "9"], "--task 9"),
    (["--env", "nowhere"], "nowhere"),
    (["--checkpoint", "no_such.pt"], "no_such.pt"),
    (["--time-limit", "-1"], "--time-limit"),
    (["--workers", "-1"], "--workers=-1"),
    (["--risk", "--risk-horizon", "0.05"], "--risk-horizon 0.05: expected at least one control period"),
    (["--risk-horizon", "3"], "--risk-horizon 3 without --risk"),
])
def test_gate_signals_refuses_bad_input_with_exit_2(tmp_path, capsys, options, message):
    out = tmp_path / "s.npz"
    argv = ["gate-signals", "--workers", "0", "--checkpoint", "wide_bc40", "--env", "wide", "--task", "1", "--out",
            str(out)]
    code = main(argv + options)
    err = capsys.readouterr().err
    assert code == 2 and message in err, err
    assert not out.exists()


def test_rollover_warnings_time_the_last_handover_before_each_rollover(tmp_path, capsys):
    from ditch_drake.learning.gate_calibration import load_signals, rollover_warnings

    # Episode 0 rolls over at its last step (9.9 s); episode 1 reaches the goal.
    rolled = np.zeros(100)
    rolled[[20, 21]] = 1.0  # A spell of the fallback from 2.0 s, handed back after 5 calm steps.
    rolled[90:] = 1.0  # The last spell, from 9.0 s to the rollover.
    path = _signals_file(tmp_path / "s.npz", np.concatenate([rolled, np.ones(100)]))
    signals = load_signals(path)
    warnings = rollover_warnings(signals, "mean_softmax_entropy", 0.5, 0.5, calm_steps=5)
    assert warnings.shape == (1,) and warnings[0] == pytest.approx(0.9)
    # A gate that hands back within the last spell, or never hands over, gave no warning.
    assert np.isnan(rollover_warnings(signals, "mean_softmax_entropy", 2.0, 0.5, calm_steps=5)).all()
    # The gate ignores the warmup's steps: a spell that only they would start (one never handed
    # back: no step falls below -1) does not count.
    early = np.zeros(100)
    early[:2] = 1.0
    path = _signals_file(tmp_path / "early.npz", np.concatenate([early, np.ones(100)]))
    assert np.isnan(rollover_warnings(load_signals(path), "mean_softmax_entropy", 0.5, -1.0, 1, warmup_steps=3)).all()
    assert rollover_warnings(load_signals(path), "mean_softmax_entropy", 0.5, -1.0, 1)[0] == pytest.approx(9.9)
    # gate-thresholds prints them per budget.
    assert main(["gate-thresholds", str(tmp_path / "s.npz"), "--signal", "mean_softmax_entropy", "--budget",
                 "0.1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    header, row = lines[0].split(), lines[1].split()
    assert header[-3:] == ["rollovers_warned", "median_warning_s", "least_warning_s"]
    assert row[header.index("rollovers_warned")] in ("0/1", "1/1")


def test_the_signal_before_each_rollover_is_drawn_with_the_budgets_thresholds(tmp_path, capsys):
    from ditch_drake.learning.gate_calibration import load_signals, signal_before_rollovers
    from ditch_drake.learning.uncertainty import GATE_SIGNALS, SIGNAL_UNITS

    # Episode 0 rolls over at 9.9 s; episode 1 reaches the goal and is not drawn.
    rolled = np.arange(100) / 100.0
    path = _signals_file(tmp_path / "s.npz", np.concatenate([rolled, np.full(100, 5.0)]))
    traces = signal_before_rollovers(load_signals(path), "mean_softmax_entropy", 1.0)
    assert len(traces) == 1
    before_s, values = traces[0]
    assert before_s == pytest.approx(np.arange(-1.0, 0.05, 0.1)) and values == pytest.approx(rolled[-11:])
    assert main(["gate-thresholds", str(path), "--signal", "mean_softmax_entropy", "--budget", "0.05", "0.2",
                 "--figure", str(tmp_path / "f.png"), "--window", "2"]) == 0
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out.splitlines()[-1] == f"figure: {tmp_path / 'f.png'}"
    assert set(SIGNAL_UNITS) == set(GATE_SIGNALS)  # Every signal a gate reads has its axis label.
    for options, message in ((["--window", "2"], "--window 2 without --figure"),
                             (["--figure", str(tmp_path / "g.png"), "--window", "-1"], "--window=-1.0: expected"),
                             (["--figure", str(tmp_path / "g.png"), "--window", "nan"], "--window=nan: expected"),
                             (["--figure", str(tmp_path / "f.png" / "g.png")], "--figure " + str(tmp_path / "f.png"))):
        assert main(["gate-thresholds", str(path), "--signal", "mean_softmax_entropy", *options]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "g.png").exists()


def test_gate_auc_prints_each_signals_auc_at_each_horizon_from_the_file(tmp_path, capsys):
    from ditch_drake.learning.gate_calibration import load_signals, signal_aucs

    # The signal rises over the last second of the episode that rolls over: it foresees a
    # rollover within 1 s well, and within 3 s less well.
    rolled = np.zeros(100)
    rolled[90:] = 1.0
    path = _signals_file(tmp_path / "s.npz", np.concatenate([rolled, np.zeros(100)]))
    assert main(["gate-auc", str(path), "--horizon", "1", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    header, rows = lines[0].split(), [line.split() for line in lines[1:3]]
    assert header[:3] == ["horizon_s", "signal", "auc"]
    assert [(row[0], row[1]) for row in rows] == [("1", "mean_softmax_entropy"), ("3", "mean_softmax_entropy")]
    expected = [signal_aucs(load_signals(path), horizon)[0]["auc"] for horizon in (1.0, 3.0)]
    assert [float(row[2]) for row in rows] == pytest.approx(expected, abs=5e-4)
    assert expected[0] > 0.9 > 0.7 > expected[1]
    for options, message in ((["--horizon", "0"], "--horizon=0.0: expected"),
                             (["--seed", "-1"], "--seed=-1: expected")):
        assert main(["gate-auc", str(path), *options]) == 2
        assert message in capsys.readouterr().err
    assert main(["gate-auc", str(tmp_path / "nowhere.npz")]) == 2


def test_gate_thresholds_prints_what_the_gate_would_set(tmp_path, capsys):
    values = np.random.default_rng(3).gamma(4.0, 0.3, 1000)
    path = _signals_file(tmp_path / "s.npz", values)
    assert main(["gate-thresholds", str(path), "--signal", "mean_softmax_entropy", "--budget", "0.05", "0.2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    header, rows = lines[0].split(), [line.split() for line in lines[1:3]]
    assert header[:3] == ["budget", "upper_threshold", "lower_threshold"] and [row[0] for row in rows] == ["0.05", "0.2"]
    gate = SharedControlConfig(signal="mean_softmax_entropy", budget=0.2, calibration=str(path)).resolved()
    assert float(rows[1][1]) == pytest.approx(gate.upper_threshold, rel=1e-3)
    assert float(rows[1][header.index("replayed_share")]) <= 0.2 < float(rows[1][header.index(
        "replayed_share_quantile_rule")])
    assert main(["gate-thresholds", str(path), "--signal", "vote_entropy"]) == 2
    assert "has no signal 'vote_entropy'" in capsys.readouterr().err
