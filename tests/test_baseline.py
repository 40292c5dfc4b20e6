"""The baseline report's pieces: the way around a ditch, the picture, the page (no simulation)."""

import math

import numpy as np

from ditch_drake.docs_tools.baseline_page import (
    BEGIN_MARK,
    END_MARK,
    DwaEpisode,
    DwaSnapshot,
    baseline_page,
    detour_length_m,
    ditch_length_to_block_m,
    replace_generated_section,
    save_snapshot_figure,
)
from ditch_drake.planning.costmap import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain, TerrainParams


def small_ditch() -> DitchTerrain:
    return DitchTerrain(TerrainParams(course="line", length_m=10.0, bottom_width_m=2.0, depth_m=1.0,
                                      field_margin_m=5.0))


def test_the_way_around_a_ditch_is_straight_on_one_side_and_round_its_end_across_it():
    terrain = small_ditch()
    same_side = detour_length_m(terrain, np.array([-6.0, -5.0]), np.array([6.0, -5.0]), clearance_m=0.3)
    assert abs(same_side - 12.0) < 0.3  # A straight line (grid paths are a little longer).
    across = detour_length_m(terrain, np.array([0.0, -5.0]), np.array([0.0, 5.0]), clearance_m=0.3)
    # Exact: tangents from start and goal to the keep-out circle round the course's end at (5, 0),
    # and the arc between them.
    radius, centre_distance = terrain.hinge_distance_m + 0.3, math.hypot(5.0, 5.0)
    tangent = math.sqrt(centre_distance**2 - radius**2)
    arc = radius * (2.0 * math.pi - 2.0 * math.acos(radius / centre_distance) - math.pi / 2)
    exact = 2.0 * tangent + arc
    assert exact - 0.05 < across < exact + 0.6  # The grid's cells keep it up to a cell off the circle.


def test_the_blocking_length_makes_the_way_around_longer_than_the_limit():
    terrain = small_ditch()
    start, goal = np.array([0.0, -5.0]), np.array([0.0, 5.0])
    length = ditch_length_to_block_m(terrain, start, goal, clearance_m=0.3, detour_limit_m=60.0, longest_m=80.0)
    assert 10.0 < length < 80.0
    from dataclasses import replace

    def around(course_length):
        return detour_length_m(DitchTerrain(replace(terrain.params, length_m=course_length)), start, goal, 0.3,
                               cell_m=0.5)

    assert around(length) > 60.0 >= around(length - 2.0)


def fake_episode(environment: str = "narrow") -> DwaEpisode:
    costs = np.full((200, 200), float(NO_INFORMATION))
    costs[60:100, 80:120] = FREE_SPACE
    costs[100:110, 70:130] = LETHAL_OBSTACLE
    trajectory = np.c_[np.zeros(10), np.linspace(-8.0, -7.0, 10), np.full(10, math.pi / 2)]
    snapshot = DwaSnapshot(time_s=4.0, pose=np.array([0.0, -8.0, math.pi / 2]), command=np.array([1.0, 0.1]),
                           origin_xy=np.array([-10.0, -18.0]), costs=costs, resolution=0.1,
                           path_xy=np.c_[np.linspace(0.0, 3.0, 20), np.linspace(-8.0, -4.0, 20)],
                           trajectory=trajectory, edge_distance_m=1.0)
    outcome = EpisodeOutcome("reached_goal", 50.0, 48.0, 3.0, 4.0, 5.0, 50.0, (0.0, 9.0))
    track = np.c_[np.linspace(0, 50, 50), np.r_[np.linspace(0, 21, 25), np.linspace(21, 0, 25)],
                  np.linspace(-9.0, 9.0, 50)]
    return DwaEpisode(environment, 0, 0, outcome, track, 1.5, np.array([0.0, -5.8]),
                      {"halts": 2, "plans": 50, "plan_failures": 0, "recoveries": 0}, snapshot, 12.0)


def test_the_snapshot_picture_is_written(tmp_path):
    path = save_snapshot_figure(fake_episode(), tmp_path)
    assert path.name == "dwa_narrow.png" and path.stat().st_size > 10_000


def test_the_page_reports_the_measured_pieces():
    speed = {"dwa_update_ms": 7.5, "dwa_update_cpu_ms": 7.25, "dwa_update_p90_ms": 9.0, "dwa_global_plan_ms": 11.0,
             "dwa_step_ms": 8.0}
    geometry = [{"environment": "narrow", "task": 0, "straight_m": 18.0, "length_m": 30.0, "span_m": 38.6,
                 "around_m": 49.3, "around_s": 49.3, "blocking_length_m": 101.5}]
    notes = {"machine": "2 cores", "load": "1.0, 1.0, 1.0", "approach_m": 1.0, "time_limit_s": 120.0,
             "clearance_m": 0.34, "speed_mps": 1.0, "wall_deg": "55"}
    page = baseline_page([fake_episode()], speed, geometry, {"narrow": "img/dwa_narrow.png"}, "img/dwa_episodes.png",
                         "python -m ditch_drake.docs_tools.baseline_page", notes)
    assert "| costmap update + DWA local plan, median wall | `dwa_update_ms` | 7.50 |" in page
    assert "1 of 1 episodes reached the goal; 0 went over a ditch's edge" in page
    assert "| narrow | reached_goal | 50.0 | 48.0 | 5.0 | 1.50 | (0.0, -5.8) | drove around the east end |" in page
    assert "![DWA in narrow](img/dwa_narrow.png)" in page
    assert "| narrow | 0 | 18.0 | 30.0 | 38.6 | 49.3 | 49 | 102 |" in page
    assert get_environment("narrow").terrain.slope_deg == 55.0
    assert page.startswith(BEGIN_MARK) and page.endswith(END_MARK)


def test_the_generated_part_replaces_only_itself():
    written = "# Title\n\nWritten by hand.\n"
    first = replace_generated_section(written, f"{BEGIN_MARK}\nold\n{END_MARK}")
    assert first.startswith(written.rstrip("\n")) and "old" in first
    second = replace_generated_section(first + "\nMore by hand.\n", f"{BEGIN_MARK}\nnew\n{END_MARK}")
    assert "old" not in second and "new" in second and second.endswith("More by hand.\n")
    assert second.startswith("# Title\n\nWritten by hand.")


def test_figure_dwa_command_draws_the_planner_at_the_ditch(tmp_path, capsys):
    from ditch_drake.cli import main

    assert main(["figure", "dwa", "--env", "narrow", "--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "dwa_narrow.png")
    assert (tmp_path / "dwa_narrow.png").stat().st_size > 10_000
