"""The packaged search environments (a ditch crossable only through windows) and the bad
environments files with slope sections: refused with exit code 2, naming environment and key."""

import dataclasses
from pathlib import Path

import pytest

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.learning.checkpoint import environment_model
from ditch_drake.world.bypass import check_no_bypass, rasterize_field
from ditch_drake.world.environments import environment_names, get_environment, load_environments
from ditch_drake.world.terrain import DitchTerrain

REPO = Path(__file__).resolve().parents[1]
SEARCH = ["wide_search", "wide_search_offset"]


@pytest.mark.parametrize("name", SEARCH)
def test_a_search_environment_is_the_fenced_wide_ditch_with_one_window_per_wall(name):
    environment = get_environment(name)  # proven: no bypass, a way in and out for each task
    assert name not in environment_names() and name in environment_names(variants=True)
    assert environment.based_on == "wide_walled" and environment_model(name) == "wide"
    assert environment.tasks == get_environment("wide").tasks
    terrain = DitchTerrain(environment.terrain)
    assert terrain.sectioned and terrain.walled
    grid = rasterize_field(terrain)
    for task in environment.tasks:
        check_no_bypass(terrain, task.start[:2], task.goal, grid)
    start = terrain.course_xy[0, 0]
    windows = {}
    for side in ("right", "left"):
        sections = terrain.slope_sections(side)
        assert all(s.slope_deg in (50.0, 70.0) for s in sections)
        (window,) = [s for s in sections if s.slope_deg == 50.0]
        windows[side] = (start + window.from_m, start + window.to_m)
        # Away from where every task's straight line crosses the ditch (x = 0).
        assert windows[side][1] <= -5.0 or windows[side][0] >= 5.0
    assert (windows["right"] == windows["left"]) == (name == "wide_search")


def _write(tmp_path, right: str, left: str = "", name: str = "notch", course: str = "line") -> Path:
    """An environments file of one 40 m ditch with the given sections, fenced as wide_search (so that
    a way in or out must use the ditch's own walls, not go round its end)."""
    path = tmp_path / f"{name}.yaml"
    slopes = f"        right: {right}\n" + (f"        left: {left}\n" if left else "")
    walls = ("      walls:\n        - points: [[-31, -14], [31, -14], [31, 14], [-31, 14], [-31, -14]]\n"
             "        - points: [[24.2, 0], [31, 0]]\n        - points: [[-24.2, 0], [-31, 0]]\n")
    path.write_text(
        f"environments:\n  {name}:\n    terrain:\n      course: {course}\n      length_m: 40.0\n"
        f"      bottom_width_m: 6.0\n      slope_deg: 70.0\n{walls}      wall_slopes:\n{slopes}"
        "    tasks: [{name: across, start: [-12.0, -11.0, 90.0], goal: [-12.0, 11.0]}]\n")
    return path


WINDOW = "[{from_m: 0, to_m: 10, slope_deg: 70}, {from_m: 10, to_m: 25, slope_deg: 50}, {from_m: 25, to_m: 40, slope_deg: 70}]"
NARROW_WINDOW = ("[{from_m: 0, to_m: 10, slope_deg: 70}, {from_m: 10, to_m: 10.5, slope_deg: 50}, "
                 "{from_m: 10.5, to_m: 40, slope_deg: 70}]")


def test_a_ditch_with_windows_loads_from_a_file(tmp_path):
    environment = load_environments(_write(tmp_path, WINDOW, WINDOW))["notch"]
    assert [s.slope_deg for s in environment.terrain.wall_slopes.right] == [70, 50, 70]


@pytest.mark.parametrize("right, left, named", [
    ("[{from_m: 0, to_m: 10, slope_deg: 70}, {from_m: 10, to_m: 40, slope_deg: 90}]", WINDOW,
     "wall_slopes.right[1].slope_deg=90.0 is out of range: expected 0 < slope_deg < 90"),
    ("[{from_m: 0, to_m: 12, slope_deg: 70}, {from_m: 10, to_m: 40, slope_deg: 50}]", WINDOW,
     "wall_slopes.right[1].from_m=10.0 is out of range: expected 12, right[0]'s end: it overlaps"),
    ("[{from_m: 0, to_m: 10, slope_deg: 70}, {from_m: 11, to_m: 40, slope_deg: 50}]", WINDOW,
     "wall_slopes.right[1].from_m=11.0 is out of range: expected 10, right[0]'s end: it leaves a gap of 1 m"),
    (WINDOW, "[{from_m: 0, to_m: 30, slope_deg: 50}]",
     "wall_slopes.left[0].to_m=30.0 is out of range: expected length_m=40"),
    (NARROW_WINDOW, WINDOW,
     ("terrain.wall_slopes.right[1]: a window (no steeper than max_traversable_slope_deg=59.6 deg) from 10 to "
      "10.5 m is 0.50 m wide; expected at least the robot's width, 0.67 m")),
    ("[{from_m: 0, to_m: 40, slope_deg: 70}]", WINDOW, "task 'across': no way in: no route from the start"),
    (WINDOW, "[{from_m: 0, to_m: 40, slope_deg: 65}]", "task 'across': no way out: no route from the goal"),
])
def test_a_bad_file_exits_2_naming_the_environment_and_the_key(tmp_path, capsys, right, left, named):
    path = _write(tmp_path, right, left)
    with pytest.raises(ConfigError) as error:
        load_environments(path)
    assert "environment 'notch'" in str(error.value) and named in str(error.value)
    code = main(["evaluate", "--controller", "edge_angle", "--environments", str(path), "--env", "notch",
                 "--rollouts", "1", "--out", str(tmp_path / "r.jsonl")])
    assert code == 2
    message = capsys.readouterr().err
    assert "'notch'" in message and named in message and message.count("\n") == 1
    assert not (tmp_path / "r.jsonl").exists()


def test_sections_on_a_winding_course_are_refused(tmp_path):
    path = _write(tmp_path, "[{from_m: 0, to_m: 40, slope_deg: 50}]", course="sine")
    with pytest.raises(ConfigError, match=r"'notch'.*wall_slopes.right is set for course='sine'"):
        load_environments(path)


def test_the_slope_sweep_example_loads_with_its_steep_and_crossable_sections():
    environments = load_environments(REPO / "examples" / "slope_sections.yaml")
    sweep = DitchTerrain(environments["slope_sweep"].terrain)
    assert [float(sweep.section_slope_deg(xy)) for xy in ([-22.0, -4.0], [2.0, -4.0], [-22.0, 4.0])] == [
        70.0, 50.0, 50.0]
    steep = dataclasses.replace(environments["slope_sweep_65"].terrain)
    assert DitchTerrain(steep).section_slope_deg([-22.0, -4.0]) == 65.0
