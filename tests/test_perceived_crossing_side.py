"""The crossing side perceived from the lidar's rays against the oracle's, on synthetic clouds."""

import math

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.perception import BaseField, Fields, PointCloud

from ditch_drake.common.errors import ConfigError
from ditch_drake.perception.lidar_model import LidarConfig
from ditch_drake.spec import robot
from ditch_drake.systems.lidar import DepthImagesToLidarCloud
from ditch_drake.systems.perceived_crossing_side import PerceivedCrossingSide, PerceivedCrossingSideConfig
from ditch_drake.world.crossing import crossing_side_step
from ditch_drake.world.terrain import DitchTerrain, TerrainParams

# A coarser lidar than the default keeps the ray casting below cheap; the block takes any rays.
LIDAR = LidarConfig(width=32, height=24)
ARC_RADIUS_M = 15.0


def _distance_to_course(course: str, xy: np.ndarray) -> np.ndarray:
    """Planar distance to the course near its middle: the line along x, or the arc about (0, R)."""
    if course == "line":
        return np.abs(xy[..., 1])
    return np.abs(np.linalg.norm(xy - [0.0, ARC_RADIUS_M], axis=-1) - ARC_RADIUS_M)


def _cloud(terrain: DitchTerrain, course: str, converter: DepthImagesToLidarCloud, X_WB: RigidTransform) -> PointCloud:
    """The organized cloud the lidar would return at X_WB: each ray marched to the first point
    below the ditch's profile, within range (NaN where none)."""
    X_BL = RigidTransform(robot.LIDAR_MOUNT_XYZ_M)
    X_WL = X_WB.multiply(X_BL)
    rays_L = converter.ray_directions_L
    rays_W = rays_L @ X_WL.rotation().matrix().T
    steps = np.arange(0.05, LIDAR.range_m + 1e-9, 0.02)
    points_W = X_WL.translation() + steps[None, :, None] * rays_W[:, None, :]
    ground = terrain.profile_height(_distance_to_course(course, points_W[..., :2]))
    below = points_W[..., 2] <= ground
    first = np.where(below.any(axis=1), below.argmax(axis=1), -1)
    ranges = np.where((first >= 0) & np.isfinite(rays_L[:, 0]), steps[np.maximum(first, 0)], np.nan)
    cloud = PointCloud(len(rays_L), Fields(BaseField.kXYZs))
    cloud.mutable_xyzs()[:] = (np.nan_to_num(rays_L) * ranges[:, None]).T
    return cloud


def _drive(course: str, bank_sign: float, goal_turn_deg: float) -> list[tuple[float, float, float]]:
    """(distance to the hinge line, perceived side, oracle side) along a straight approach to the
    ditch from the bank on `bank_sign`'s side, facing square on, toward a goal turned
    `goal_turn_deg` from square across."""
    terrain = DitchTerrain(TerrainParams(course=course, arc_radius_m=ARC_RADIUS_M, length_m=30.0))
    converter = DepthImagesToLidarCloud(LIDAR)
    hinge = terrain.hinge_distance_m
    # Both courses pass through the origin heading +x (the arc bends toward +y, its inside).
    center, normal = np.zeros(2), np.array([0.0, bank_sign])
    toward = -normal
    turn = math.radians(goal_turn_deg)
    across = np.array([math.cos(turn) * toward[0] - math.sin(turn) * toward[1],
                       math.sin(turn) * toward[0] + math.cos(turn) * toward[1]])
    goal = center + 2.0 * hinge * toward + 15.0 * across
    block = PerceivedCrossingSide(goal_xy=goal, chassis_body_index=0, X_BL=RigidTransform(robot.LIDAR_MOUNT_XYZ_M),
                                  ray_directions_L=converter.ray_directions_L, lidar_range_m=LIDAR.range_m)
    context = block.CreateDefaultContext()
    yaw = math.atan2(toward[1], toward[0])
    held = 0.0
    drive = []
    for edge_m in [8.0, *np.arange(4.5, 2.4, -0.1)]:
        xy = center + (hinge + edge_m) * normal
        X_WB = RigidTransform(RollPitchYaw(0.0, 0.0, yaw), [*xy, robot.WHEEL_RADIUS_M])
        block.get_input_port(0).FixValue(context, _cloud(terrain, course, converter, X_WB))
        block.get_input_port(1).FixValue(context, [X_WB])
        context.SetDiscreteState(block.EvalUniquePeriodicDiscreteUpdate(context))
        oracle, held = crossing_side_step(terrain, xy, goal, held, 2.5, 15.0)
        drive.append((edge_m, float(block.GetOutputPort("crossing_side").Eval(context)[0]), oracle))
    return drive


@pytest.mark.parametrize("course", ["line", "arc"])
@pytest.mark.parametrize("bank_sign", [1.0, -1.0])
@pytest.mark.parametrize("goal_turn_deg", [-50.0, 50.0])
def test_perceived_side_equals_the_oracle_once_the_edge_is_in_view(course, bank_sign, goal_turn_deg):
    drive = _drive(course, bank_sign, goal_turn_deg)
    assert drive[0][1] == 0.0  # 8 m from the hinge line: beyond the lidar's 4 m.
    seen = [(edge_m, perceived, oracle) for edge_m, perceived, oracle in drive if perceived != 0.0]
    assert seen and seen[0][0] >= 3.0, drive  # In view before the approach zone (2.5 m).
    assert all(perceived == oracle for _, perceived, oracle in seen), drive


@pytest.mark.parametrize("course", ["line", "arc"])
def test_perceived_side_follows_the_goal_and_holds_near_square(course):
    assert {_drive(course, 1.0, turn)[-1][1] for turn in (-50.0, 50.0)} == {-1.0, 1.0}
    assert _drive(course, -1.0, 5.0)[-1][1] == 1.0  # Within the convention's 15 deg: right.


def test_config_out_of_range_is_named():
    with pytest.raises(ConfigError, match="band_m"):
        PerceivedCrossingSideConfig(band_m=0.0).validate()
    with pytest.raises(ConfigError, match="min_marks"):
        PerceivedCrossingSideConfig(min_marks=0).validate()


def test_the_benchmark_times_the_update_on_a_short_replay():
    from ditch_drake.perf.bench_crossing_side import measure_crossing_side_ms
    from ditch_drake.perf.recorded_drive import record_lidar_drive

    drive = record_lidar_drive("wide", 1, 0, 1.0)  # Task 1 starts in view of the edge.
    figures = measure_crossing_side_ms(drive, repeats=1)
    assert figures["crossing_side_steps"] == len(drive.clouds) - 1
    assert 0 < figures["crossing_side_seen_steps"] <= figures["crossing_side_steps"]
    for key in ("crossing_side_ms", "crossing_side_cpu_ms", "crossing_side_p90_ms"):
        assert 0.0 < figures[key] < 1000.0, key


def test_the_command_line_offers_the_configs_sources_and_refuses_them_for_other_controllers(capsys, tmp_path):
    from ditch_drake.cli import options
    from ditch_drake.cli.main import main
    from ditch_drake.diagrams.rollout import CROSSING_SIDE_SOURCES, LearnedPolicyConfig

    assert options.CROSSING_SIDE_SOURCES == CROSSING_SIDE_SOURCES
    config = options.learned_with_crossing_side("learned", "generalist", "oracle")
    assert isinstance(config, LearnedPolicyConfig) and (config.checkpoint, config.crossing_side) == (
        "generalist", "oracle")
    assert options.learned_with_crossing_side("dwa", "", None) == "dwa"
    assert main(["evaluate", "--controller", "dwa", "--env", "wide", "--crossing-side", "oracle",
                 "--rollouts", "1", "--out", str(tmp_path / "x.jsonl")]) == 2
    assert "crossing_side 'oracle' with a DwaBaselineConfig" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="crossing_side='map'"):
        LearnedPolicyConfig(crossing_side="map").validate()
