"""`ditch-drake paired`: two runs compared rollout by rollout (McNemar's exact test), from synthetic
records of known outcomes, and its bad inputs."""

import json

from scipy.stats import binomtest

from ditch_drake.cli import main
from ditch_drake.evaluation.results import RolloutRecord
from ditch_drake.evaluation.statistics import paired_comparison


def record(env: str, task: int, success: bool, controller: str = "shared", status: str = "") -> RolloutRecord:
    return RolloutRecord(
        key=f"{controller}|{env}|{task}|0", controller=controller, checkpoint="", environment=env, task=task, seed=0,
        time_limit_s=120.0, goal_radius_m=1.5, checkpoint_sha256="",
        status=status or ("reached_goal" if success else "rolled_over"), success=success, time_s=60.0,
        path_length_m=30.0, peak_abs_roll_deg=5.0, peak_abs_pitch_deg=30.0, peak_tilt_deg=31.0,
        min_stability_margin_deg=10.0, final_x_m=0.0, final_y_m=0.0, failure_region="" if success else "down_wall",
        wall_s=1.0)


def runs() -> tuple[list[RolloutRecord], list[RolloutRecord]]:
    """12 shared ditches: both succeed in 5, neither in 1, only the first in 5, only the second in 1;
    the first has an error record and a ditch the second lacks, the second one the first lacks."""
    a = ([record(f"d{i}", 0, True) for i in range(5)] + [record("d5", 0, False)]
         + [record(f"d{i}", 0, True) for i in range(6, 11)] + [record("d11", 0, False), record("d12", 0, True),
                                                                 record("d13", 0, False, status="error")])
    b = ([record(f"d{i}", 0, True) for i in range(5)] + [record("d5", 0, False)]
         + [record(f"d{i}", 0, False) for i in range(6, 11)] + [record("d11", 0, True), record("d14", 0, True)])
    return a, b


def test_the_paired_comparison_counts_the_rollouts_where_the_runs_differ():
    comparison = paired_comparison(*runs())
    assert (comparison.matched, comparison.both, comparison.neither, comparison.only_a, comparison.only_b) == (
        12, 5, 1, 5, 1)
    assert (comparison.unmatched_a, comparison.unmatched_b) == (1, 1)  # d12; d14 (d13's error counts nowhere).
    assert comparison.p_value == binomtest(5, 6).pvalue == 0.21875
    a, _ = runs()
    assert paired_comparison(a, a).p_value == 1.0 and paired_comparison(a, a).only_a == 0


def _write(path, records):
    path.write_text("".join(r.to_json() + "\n" for r in records))
    return str(path)


def test_the_command_prints_one_json_object(tmp_path, capsys):
    a, b = runs()
    assert main(["paired", _write(tmp_path / "a.jsonl", a), _write(tmp_path / "b.jsonl", b)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert (printed["matched"], printed["only_a"], printed["only_b"], printed["p_value"]) == (12, 5, 1, 0.21875)


def test_bad_inputs_exit_2_naming_the_file(tmp_path, capsys):
    a, b = runs()
    first = _write(tmp_path / "a.jsonl", a)
    assert main(["paired", first, str(tmp_path / "none.jsonl")]) == 2
    assert "no results file at" in capsys.readouterr().err
    mixed = _write(tmp_path / "mixed.jsonl", [*b, record("d0", 0, True, controller="learned")])
    assert main(["paired", first, mixed]) == 2
    assert "mixed.jsonl holds rollouts of 2 controllers or checkpoints" in capsys.readouterr().err
    apart = _write(tmp_path / "apart.jsonl", [record("elsewhere", 0, True)])
    assert main(["paired", first, apart]) == 2
    assert "share no rollout" in capsys.readouterr().err


def gated(env: str, success: bool, signal: str, budget: float, fallback: str = "mppi") -> RolloutRecord:
    """A shared-control record of `env` task 0 seed 0 whose config's gate has these values; each
    environment's series has a config (thresholds) of its own, as an experiment's have."""
    from dataclasses import replace

    config = f"policy: {{checkpoint: {env}_k5.pt}}\ngate:\n  signal: {signal}\n  budget: {budget}\n  fallback: {fallback}\n"
    return replace(record(env, 0, success), controller_config=config, controller_sha256=f"{env}{signal}{budget}")


def test_where_takes_one_series_from_a_file_of_several(tmp_path, capsys):
    # Four environments; at 5 % the gate crosses d0-d2 and random handover d0 and d3; the 20 %
    # series and an ungated run are in the same file and are left out.
    study = ([gated(f"d{i}", i < 3, "angular_rate_spread", 0.05) for i in range(4)]
             + [gated(f"d{i}", i in (0, 3), "random", 0.05) for i in range(4)]
             + [gated(f"d{i}", False, "random", 0.2) for i in range(4)]
             + [record(f"d{i}", 0, True, controller="learned") for i in range(4)])
    path = _write(tmp_path / "study.jsonl", study)
    assert main(["paired", path, path, "--a-where", "signal=angular_rate_spread", "--b-where",
                 "signal=random,budget=0.050,fallback=mppi"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert (printed["matched"], printed["both"], printed["neither"], printed["only_a"], printed["only_b"]) == (
        4, 1, 0, 2, 1)
    assert (printed["a_where"], printed["b_where"]) == ("signal=angular_rate_spread", "signal=random,budget=0.050,fallback=mppi")
    assert main(["paired", path, path, "--a-where", "controller=learned", "--b-where", "budget=0.2"]) == 0
    assert json.loads(capsys.readouterr().out)["only_a"] == 4
    # Without a selection the file holds several runs; a selection of two runs, or of none, or
    # a term that is not KEY=VALUE of a known key, is refused, naming what was given.
    for where, words in ((None, "or --a-where to select one"),
                         ("signal=random", "selects 4 rollouts of"),
                         ("fallback=expert", "no record of"),
                         ("checkpoint=x", "'checkpoint=x' is not KEY=VALUE with KEY one of controller"),
                         ("budget=five", "budget 'five' is not a number")):
        assert main(["paired", path, path, *(["--a-where", where] if where else []), "--b-where",
                     "controller=learned"]) == 2
        assert words in capsys.readouterr().err
