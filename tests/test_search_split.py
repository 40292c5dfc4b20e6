"""The search splits: straight ditches whose steep walls are crossable only through windows,
drawn from `search_ranges.yaml` (ditch_drake/benchmark/generator.py, ranges.py, splits.py)."""

import itertools

import numpy as np
import pytest

from ditch_drake.benchmark.generator import WINDOW_GAP_M, sample_ditch
from ditch_drake.benchmark.ranges import (
    BenchmarkRanges,
    WindowRanges,
    all_headings_tip_angle_deg,
    load_ranges,
    packaged_ranges_path,
)
from ditch_drake.benchmark.run import BenchmarkConfig, benchmark_specs
from ditch_drake.benchmark.splits import (
    SEED_SPLITS,
    SPLIT_RANGES,
    ditches_file,
    split_of_environment,
    split_ranges,
    split_seeds,
)
from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError, TerrainError
from ditch_drake.diagrams.ditch_scene import MakeDitchDiagram, SceneConfig
from ditch_drake.world.bypass import check_no_bypass
from ditch_drake.world.environments import load_environments, validate_environment
from ditch_drake.world.ingress import check_ways_in_and_out, smallest_tip_angle_deg
from ditch_drake.world.terrain import WALL_SIDES, DitchTerrain, SlopeSection

# The search ditches checked one by one: the first of each search split's seeds.
CHECKED_SEEDS = (4000, 4001, 4002, 4003, 4100, 4101)


@pytest.fixture(scope="module")
def search_ranges():
    return split_ranges("search")


@pytest.fixture(scope="module")
def search_ditches(search_ranges):
    return {seed: sample_ditch(seed, search_ranges) for seed in CHECKED_SEEDS}


def windows_of(terrain, side: str) -> list[SlopeSection]:
    return [s for s in getattr(terrain.params.wall_slopes, side) if s.slope_deg != terrain.params.slope_deg]


def test_the_search_splits_have_their_seeds_and_the_search_ranges():
    assert SEED_SPLITS["search"] == range(4000, 4100) and SEED_SPLITS["search_val"] == range(4100, 4150)
    assert split_seeds("search", 2) == [4000, 4001] and split_seeds("search_val") == list(range(4100, 4150))
    assert split_of_environment("ditch_4042") == "search" and split_of_environment("ditch_4149") == "search_val"
    assert split_of_environment("ditch_4150") == ""
    seeds = [set(values) for values in SEED_SPLITS.values()]
    assert sum(len(values) for values in seeds) == len(set().union(*seeds))  # disjoint
    assert SPLIT_RANGES["search"] == SPLIT_RANGES["search_val"] == "search_ranges.yaml"
    packaged = load_ranges(packaged_ranges_path("search_ranges.yaml"))
    assert split_ranges("search") == split_ranges("search_val") == packaged
    assert packaged.course_kinds == ["line"] and packaged.windows == WindowRanges(
        per_wall=[1, 2], width_m=[8.0, 20.0], slope_deg=[45.0, 55.0], end_margin_m=5.0, line_margin_m=3.0)
    assert packaged.slope_deg[0] > all_headings_tip_angle_deg() > 68.0
    assert packaged.windows.slope_deg[1] < smallest_tip_angle_deg()


def test_a_search_seed_always_gives_the_same_ditch(search_ranges, search_ditches):
    for seed in (4000, 4100):
        again = sample_ditch(seed, search_ranges)
        assert again == search_ditches[seed] and again.name == f"ditch_{seed}"
    assert search_ditches[4000].environment != search_ditches[4001].environment


@pytest.mark.parametrize("seed", CHECKED_SEEDS)
def test_a_search_ditch_has_windows_within_its_ranges_off_the_tasks_lines_and_ways_in_and_out(
        search_ranges, search_ditches, seed):
    environment = search_ditches[seed].environment
    params, windows = environment.terrain, search_ranges.windows
    assert params.course == "line" and len(environment.tasks) == 3
    assert search_ranges.slope_deg[0] <= params.slope_deg <= search_ranges.slope_deg[1]
    assert search_ranges.course_length_m[0] <= params.length_m <= search_ranges.course_length_m[1]
    terrain = DitchTerrain(params)
    for side in WALL_SIDES:
        sections = getattr(params.wall_slopes, side)
        assert sections[0].from_m == 0.0 and sections[-1].to_m == params.length_m
        assert all(a.to_m == b.from_m for a, b in itertools.pairwise(sections))
        found = windows_of(terrain, side)
        assert windows.per_wall[0] <= len(found) <= windows.per_wall[1]
        for window in found:
            assert windows.slope_deg[0] <= window.slope_deg <= windows.slope_deg[1]
            assert windows.width_m[0] <= window.to_m - window.from_m <= windows.width_m[1] + 1e-9
            assert window.from_m >= windows.end_margin_m and window.to_m <= params.length_m - windows.end_margin_m
        assert all(b.from_m - a.to_m >= WINDOW_GAP_M - 1e-3 for a, b in itertools.pairwise(found))
    for task in environment.tasks:
        # A controller that drives the straight line meets steep wall on both sides.
        start, goal = np.array(task.start[:2]), np.array(task.goal)
        line = start + np.linspace(0.0, 1.0, 2001)[:, None] * (goal - start)
        distance = terrain.nearest_on_course(line)[0]
        on_walls = (distance > terrain.toe_distance_m) & (distance < terrain.hinge_distance_m)
        assert np.all(terrain.section_slope_deg(line[on_walls]) == params.slope_deg)
    validate_environment(environment)  # the family's limits, the windows' widths and both proofs
    for task in environment.tasks:
        check_ways_in_and_out(terrain, task.start[:2], task.goal)
        check_no_bypass(terrain, task.start[:2], task.goal)


# Draws of the existing splits before the search splits were added: (seed, split, draw, course,
# [slope, bottom, depth, hinge radius, length, sine amplitude, sine wavelength, arc radius],
# each task's start and goal, the first end (or dividing) wall).
EXISTING_DRAWS = [
    (0, "train", 0, "point", [45.41, 11.627, 3.033, 0.408, 30.0, 0.0, 30.0, 15.0],
     [[6.807, 15.322, -115.7, -7.807, -15.041], [1.202, 14.903, -95.7, -1.759, -14.746],
      [-0.673, -14.592, 84.3, 2.199, 14.163]], [[-7.841, 2.205], [-20.241, 5.691]]),
    (123, "train", 0, "line", [47.204, 3.055, 3.369, 0.322, 34.121, 0.0, 30.0, 15.0],
     [[-0.667, 11.467, -99.68, -4.579, -11.467], [-7.67, 11.818, -61.15, 5.35, -11.818],
      [8.009, 10.623, -98.12, 4.979, -10.623]], [[20.989, 0.0], [33.089, 0.0]]),
    (1003, "val", 0, "sine", [49.947, 6.513, 4.322, 0.403, 33.231, 1.706, 26.809, 15.0],
     [[10.965, -14.452, 134.29, -18.218, 15.459], [-6.239, 12.536, -56.81, 11.068, -13.918],
      [5.959, 14.213, -90.31, 5.822, -11.164]], [[22.581, -3.082], [34.976, -7.064]]),
    (2042, "test", 0, "arc", [52.926, 3.545, 3.11, 0.417, 35.394, 0.0, 30.0, 19.582],
     [[-14.187, -9.067, 52.7, 2.333, 12.621], [-1.254, 10.118, -71.89, 5.177, -9.545],
      [10.367, -9.294, 122.1, -2.618, 11.41]], [[17.71, 10.133], [29.003, 23.08]]),
    (3017, "stress", 0, "line", [56.435, 1.98, 5.227, 0.627, 30.772, 0.0, 30.0, 15.0],
     [[-15.834, 11.271, -45.24, 6.517, -11.271], [-10.238, -11.806, 47.96, 11.053, 11.806],
      [13.274, -10.603, 129.63, -4.287, 10.603]], [[19.517, 0.0], [31.617, 0.0]]),
]


@pytest.mark.parametrize("seed, split, draw, course, numbers, tasks, wall", EXISTING_DRAWS)
def test_the_existing_splits_draw_the_ditches_they_drew_before(seed, split, draw, course, numbers, tasks, wall):
    ditch = sample_ditch(seed, split_ranges(split))
    params = ditch.environment.terrain
    assert ditch.draw == draw and params.course == course
    assert [params.slope_deg, params.bottom_width_m, params.depth_m, params.hinge_radius_m, params.length_m,
            params.sine_amplitude_m, params.sine_wavelength_m, params.arc_radius_m] == numbers
    assert [task.start + task.goal for task in ditch.environment.tasks] == tasks
    assert params.walls[1].points == wall
    assert not params.wall_slopes.right and not params.wall_slopes.left


def windowed(**changes) -> BenchmarkRanges:
    ranges = load_ranges(packaged_ranges_path("search_ranges.yaml"))
    for key, value in changes.items():
        owner = ranges.windows if key.startswith("windows.") else ranges
        setattr(owner, key.removeprefix("windows."), value)
    return ranges


@pytest.mark.parametrize("changes, message", [
    ({"windows.width_m": [0.5, 8.0]}, r"windows.width_m=\[0.5, 8.0\] is out of bounds: expected .*0.67 <= low"),
    ({"windows.width_m": [12.0, 8.0]}, r"windows.width_m=\[12.0, 8.0\] is inverted"),
    ({"windows.slope_deg": [45.0, 62.0]}, r"windows.slope_deg=\[45.0, 62.0\] is out of bounds: .*<= 59.6"),
    ({"windows.per_wall": [0, 2]}, (r"windows.per_wall=\[0, 2\] is out of bounds: expected \[low, high\] of "
                                    r"integers with 1 <= low")),
    ({"windows.end_margin_m": 0.5}, r"windows.end_margin_m=0.5 is out of bounds: expected a number in \[1, 20\]"),
    ({"windows.line_margin_m": -1.0}, r"windows.line_margin_m=-1.0 is out of bounds"),
    ({"slope_deg": [65.0, 75.0]}, r"slope_deg=\[65.0, 75.0\] is out of bounds: expected .*68.4 <= low .*every heading"),
    ({"course_kinds": ["line", "sine"]}, r"course_kinds=\['line', 'sine'\] with windows: expected \[line\]"),
    ({"course_length_m": [26.0, 36.0]}, (r"course_length_m=\[26.0, 36.0\] is too short for the windows: .* at "
                                         r"least 30 m")),
    ({"course_length_m": [50.0, 90.0]}, r"course_length_m=\[50.0, 90.0\] is out of bounds"),
])
def test_bad_window_ranges_are_refused_naming_the_key(changes, message):
    with pytest.raises(ConfigError, match=message):
        windowed(**changes).validate()
    with pytest.raises(ConfigError, match=message):
        sample_ditch(4000, windowed(**changes))


def test_a_bad_search_ranges_file_exits_2_naming_the_key(tmp_path, capsys):
    out, ranges = str(tmp_path / "s.jsonl"), tmp_path / "ranges.yaml"
    text = packaged_ranges_path("search_ranges.yaml").read_text()
    for bad, message in (("width_m: [8.0, 20.0]", "windows.width_m=[0.3, 20.0] is out of bounds"),
                         ("width_m: [8.0, 20.0]", "unknown key 'windows.widths_m'")):
        replacement = "width_m: [0.3, 20.0]" if "out of bounds" in message else "widths_m: [8.0, 20.0]"
        ranges.write_text(text.replace(bad, replacement))
        assert main(["benchmark", "--split", "search", "--ranges", str(ranges), "--out", out]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "s.jsonl").exists()


def test_a_generated_window_narrower_than_the_robot_or_sections_that_overlap_are_refused(search_ditches):
    environment = search_ditches[4000].environment
    params = environment.terrain
    side = next(side for side in WALL_SIDES if windows_of(DitchTerrain(params), side))
    sections = getattr(params.wall_slopes, side)
    index = next(i for i, s in enumerate(sections) if s.slope_deg != params.slope_deg)
    window = sections[index]
    narrow = [SlopeSection(s.from_m, s.to_m, s.slope_deg) for s in sections]
    narrow[index - 1].to_m = narrow[index].from_m = window.to_m - 0.5
    setattr(params.wall_slopes, side, narrow)
    try:
        with pytest.raises(ConfigError, match=rf"wall_slopes.{side}\[{index}\]: a window .* 0.50 m wide"):
            validate_environment(environment)
        overlapping = [SlopeSection(s.from_m, s.to_m, s.slope_deg) for s in sections]
        overlapping[index].from_m = window.from_m - 1.0
        setattr(params.wall_slopes, side, overlapping)
        with pytest.raises(TerrainError, match=rf"wall_slopes.{side}\[{index}\].from_m=.*overlaps"):
            validate_environment(environment)
        gapped = [SlopeSection(s.from_m, s.to_m, s.slope_deg) for s in sections]
        gapped[index].from_m = window.from_m + 1.0
        setattr(params.wall_slopes, side, gapped)
        with pytest.raises(TerrainError, match=rf"wall_slopes.{side}\[{index}\].from_m=.*gap"):
            validate_environment(environment)
    finally:
        setattr(params.wall_slopes, side, sections)


def test_a_search_benchmark_run_writes_ditches_that_read_back(tmp_path, search_ditches):
    out = tmp_path / "search.jsonl"
    specs = benchmark_specs(BenchmarkConfig(split="search", controller="head_on", geometries=1, out=str(out)),
                            progress=False)
    assert [(spec.environment, spec.task) for spec in specs] == [("ditch_4000", task) for task in range(3)]
    assert load_environments(ditches_file(out))["ditch_4000"] == search_ditches[4000].environment


def test_the_cli_lists_the_search_splits(tmp_path, capsys):
    assert main(["benchmark", "--split", "holdout", "--out", str(tmp_path / "b.jsonl")]) == 2
    assert ("expected one of ['train', 'val', 'test', 'stress', 'search', 'search_val', 'paper']"
            in capsys.readouterr().err)


def test_a_search_ditch_builds_in_a_plant(search_ditches):
    ditch = search_ditches[4000]
    MakeDitchDiagram(SceneConfig(environment=ditch.name, environments={ditch.name: ditch.environment}))
