"""The halt counter on scripted command sequences, the ditch regions it counts in, and the
rollout records that carry its counts."""

import dataclasses
import json

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.rollout import ConstantCommandConfig
from ditch_drake.evaluation import rollout_worker
from ditch_drake.evaluation.batch import make_specs
from ditch_drake.evaluation.report_data import study_table
from ditch_drake.evaluation.results import SCHEMA_VERSION, RolloutRecord, read_records, record_key
from ditch_drake.evaluation.summary import summarize
from ditch_drake.systems.halt_counter import HaltCounter
from ditch_drake.world.regions import REGIONS, ditch_region
from ditch_drake.world.terrain import DitchTerrain, TerrainParams

# A straight ditch along x with a 4 m floor; the robot starts on the -y side.
TERRAIN = DitchTerrain(TerrainParams(course="line", bottom_width_m=4.0))
START_XY = (0.0, -10.0)
WALL_Y = (TERRAIN.toe_distance_m + TERRAIN.hinge_distance_m) / 2  # Halfway up a wall.
WHERE = {"approach": (0.0, -8.0), "down_wall": (0.0, -WALL_Y), "floor": (1.0, 0.5), "up_wall": (0.0, WALL_Y),
         "beyond": (0.0, 8.0)}
PERIOD_S = 0.1


def run_script(script, xy=WHERE["approach"]):
    """Counts over `script`: (seconds, v m/s[, xy]) pieces, each held from the end of the one
    before. The first piece starts at 0.05 s, between ticks, so every piece of n.5 periods
    holds over exactly the ticks inside it: 0.4 s of stop holds over 4 ticks, 0.6 s over 6."""
    counter = HaltCounter(TERRAIN, START_XY, 0, period_s=PERIOD_S)
    simulator = Simulator(counter)
    context = simulator.get_mutable_context()
    poses = counter.GetInputPort("body_poses")
    command = counter.GetInputPort("command")
    command.FixValue(context, [1.0, 0.0])
    poses.FixValue(context, [RigidTransform([*xy, 0.0])])
    simulator.AdvanceTo(0.05)
    for piece in script:
        seconds, v = piece[:2]
        command.FixValue(context, [v, 0.3])
        if len(piece) > 2:
            poses.FixValue(context, [RigidTransform([*piece[2], 0.0])])
        simulator.AdvanceTo(context.get_time() + seconds)
    return counter.halts_by_region(counter.GetMyContextFromRoot(context))


def halts(**counts):
    return {region: counts.get(region, 0) for region in REGIONS}


def test_a_stop_shorter_than_half_a_second_is_no_halt():
    assert run_script([(1.0, 1.0), (0.4, 0.0), (1.0, 1.0)]) == halts()


def test_a_stop_of_six_tenths_is_one_halt():
    assert run_script([(1.0, 1.0), (0.6, 0.0), (1.0, 1.0)]) == halts(approach=1)


def test_a_stop_of_exactly_half_a_second_is_one_halt():
    assert run_script([(1.0, 1.0), (0.5, 0.0), (1.0, 1.0)]) == halts(approach=1)


def test_two_separate_stops_are_two_halts():
    assert run_script([(0.6, 0.0), (0.3, 1.0), (0.6, 0.0), (1.0, 1.0)]) == halts(approach=2)


def test_a_long_stop_is_one_halt():
    assert run_script([(1.0, 1.0), (5.0, 0.0)]) == halts(approach=1)


def test_a_crawl_below_the_speed_is_a_stop_and_a_slow_drive_above_it_is_not():
    # |v|: a reverse crawl at 0.04 m/s is a stop; 0.06 m/s either way is driving.
    assert run_script([(0.6, -0.04), (0.2, 1.0)]) == halts(approach=1)
    assert run_script([(0.6, 0.06), (0.6, -0.06)]) == halts()


def test_a_short_blip_of_driving_splits_a_stop():
    assert run_script([(0.4, 0.0), (0.1, 0.5), (0.4, 0.0), (0.5, 1.0)]) == halts()


def test_stops_in_different_regions_count_in_their_regions():
    script = [(0.6, 0.0, WHERE["approach"]), (0.3, 1.0, WHERE["down_wall"]), (0.6, 0.0),
              (0.3, 1.0, WHERE["floor"]), (0.6, 0.0), (0.3, 1.0, WHERE["up_wall"]), (2.0, 0.0),
              (0.3, 1.0, WHERE["beyond"]), (0.6, 0.0), (0.3, 1.0), (0.6, 0.0)]
    assert run_script(script) == halts(approach=1, down_wall=1, floor=1, up_wall=1, beyond=2)


def test_a_halt_counts_where_it_reached_half_a_second_not_where_it_ended():
    # Stopped on the backslope, slid to the floor with the command still at zero.
    assert run_script([(0.3, 0.0, WHERE["up_wall"]), (0.3, 0.0), (1.0, 0.0, WHERE["floor"])]) == halts(up_wall=1)


def test_the_counts_are_an_output_in_region_order():
    counter = HaltCounter(TERRAIN, START_XY, 0, period_s=PERIOD_S)
    context = counter.CreateDefaultContext()
    assert counter.GetOutputPort("halts_by_region").Eval(context).tolist() == [0.0] * len(REGIONS)


def test_ditch_region_on_each_region_of_a_line_ditch():
    for region, xy in WHERE.items():
        assert ditch_region(TERRAIN, START_XY, xy) == region
    # Seen from the other side, the walls and the flat sides swap.
    assert [ditch_region(TERRAIN, (0.0, 10.0), WHERE[r]) for r in REGIONS] == [
        "beyond", "up_wall", "floor", "down_wall", "approach"]


def _record(**changes) -> RolloutRecord:
    record = RolloutRecord(**{
        "key": "k", "controller": "dwa", "checkpoint": "", "environment": "wide", "task": 0, "seed": 0,
        "time_limit_s": 120.0, "goal_radius_m": 1.5, "checkpoint_sha256": "", "status": "stuck", "success": False,
        "time_s": 30.0, "path_length_m": 10.0, "peak_abs_roll_deg": 1.0, "peak_abs_pitch_deg": 30.0,
        "peak_tilt_deg": 30.0, "min_stability_margin_deg": 20.0, "final_x_m": 0.0, "final_y_m": 1.0,
        "failure_region": "up_wall", "wall_s": 1.0, **changes})
    record.key = record_key(record)
    return record


def test_records_round_trip_their_halts_and_older_lines_read_without_them(tmp_path):
    record = _record(halts_by_region=halts(up_wall=2, floor=1))
    line = json.loads(record.to_json())
    assert line["schema_version"] == SCHEMA_VERSION and line["halts_by_region"]["up_wall"] == 2
    read = RolloutRecord.from_dict(line, "here")
    assert read.halts_by_region == halts(up_wall=2, floor=1) and read.key == record.key
    # A schema 4 line (before halts were counted): no field, read as not counted, same key.
    old = {key: value for key, value in line.items() if key != "halts_by_region"} | {"schema_version": 4}
    path = tmp_path / "old.jsonl"
    path.write_text(json.dumps(old) + "\n")
    (old_record,), warnings = read_records(path)
    assert old_record.halts_by_region == {} and old_record.key == record.key and warnings == []


def test_summaries_and_the_table_sum_halts_over_the_records_that_count_them():
    counted = [_record(halts_by_region=halts(up_wall=2)), _record(halts_by_region=halts(up_wall=1, floor=1))]
    summary = summarize([*counted, _record(), _record(status="error", halts_by_region=halts(beyond=9))])
    assert summary.halts_by_region == halts(up_wall=3, floor=1) and summary.halts_counted == 2
    assert summarize([_record()]).halts_by_region == {}
    lines, _ = study_table(counted)
    assert lines[0].split(" | ")[-4] == "halts (region)" and "| floor 1, up_wall 3 |" in lines[2]
    assert "| - |" in study_table([_record()])[0][2]


@pytest.fixture(scope="module")
def standing_still_spec():
    (spec,) = make_specs(ConstantCommandConfig([0.0, 0.0]), "", "wide", [0], rollouts=1, time_limit_s=2.0)
    return spec


def test_a_rollout_record_counts_the_halts_of_its_episode_afresh_each_time(standing_still_spec):
    # Standing still for the whole episode is one halt, at the start; the worker reuses its
    # diagram, and the next rollout counts from zero again.
    for seed in (0, 1):
        record = rollout_worker.run_rollout(dataclasses.replace(standing_still_spec, seed=seed))
        assert record.status == "timeout" and record.halts_by_region == halts(approach=1)
    assert rollout_worker.error_record(standing_still_spec, "boom").halts_by_region == {}
    assert np.isnan(rollout_worker.error_record(standing_still_spec, "boom").time_s)


def test_the_study_table_gives_the_median_time_and_path_length_of_the_successes_only():
    crossed = [_record(status="reached_goal", success=True, failure_region="", time_s=t, path_length_m=p, seed=s)
               for s, (t, p) in enumerate([(40.0, 20.0), (50.0, 30.0), (90.0, 70.0)])]
    lines, _ = study_table([*crossed, _record(seed=9, time_s=120.0, path_length_m=5.0)])
    assert lines[0].endswith("| errors | time (s) | path (m) |") and lines[2].endswith("| 0 | 50 | 30 |")
    assert study_table([_record()])[0][2].endswith("| - | - |")
