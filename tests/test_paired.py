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
