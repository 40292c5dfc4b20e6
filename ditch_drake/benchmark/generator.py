"""Seeded procedural ditches: `sample_ditch(seed, ranges)` gives a fenced ditch and three tasks.

A draw picks a course kind and the terrain's parameters uniformly within `BenchmarkRanges`,
fences the field so that every route crosses the ditch (a rectangle of walls, and a wall
from each end of the course along its last heading to the rectangle; for a crater, a wall
on each side from the rectangle to the rim), and lays out three tasks that cross at
different places along the course (one in each third of the stretch between 30 % and 70 % of
its length; across a crater, near its centre), each turned from the course's normal by a drawn crossing angle, their start and
goal on opposite sides, on the straight line through the crossing point, a drawn approach
distance beyond the ditch's edge (from the nearest part of the course: on a curved course the
line goes on until it is that far).

Ranges with windows (`BenchmarkRanges.windows`, the search splits') draw a straight ditch whose
walls stand at the drawn steep `slope_deg` except in windows (`TerrainParams.wall_slopes`):
after the terrain, each wall's count of windows and their slopes; the field, the end walls
(sealing against the steep rounded ends) and the tasks laid out on the ditch at its widest
(its gentlest window's); then each window's width and place, drawn among the places that keep
`end_margin_m` from the course's ends, `line_margin_m` from where each task's straight line
crosses that wall, and `WINDOW_GAP_M` from the wall's other windows, its width below the
longest stretch left. A draw with no stretch as long as the narrowest window fails like any
other. Ranges without windows draw none of these, so their ditches are the draws they always
were.

Each draw is checked the way the packaged walled environments are
(`ditch_drake.world.environments.validate_environment`: the terrain family's limits, the
tasks' clearances, the planar proof that no route bypasses the ditch and, for walls with
windows, the proof of a way in and a way out for each task, `ditch_drake.world.ingress`).
A draw that fails is replaced by the next draw of the same seed (`SampledDitch.draw` records
which one was kept); a seed whose `MAX_DRAWS` draws all fail is refused with its seed named.
The same seed and ranges always give the same ditch: draw k of seed s uses
`numpy.random.default_rng([s, k])`.
"""

import math
from dataclasses import dataclass, replace

import numpy as np

from ditch_drake.benchmark.ranges import BenchmarkRanges, WindowRanges
from ditch_drake.common.errors import ConfigError, TerrainError
from ditch_drake.world.environments import TASK_CLEARANCE_M, Environment, Task, validate_environment
from ditch_drake.world.terrain import (
    WALL_SIDES,
    DitchTerrain,
    SlopeSection,
    TerrainParams,
    Wall,
    WallSlopes,
    min_bend_radius_m,
)

MAX_DRAWS = 20
TASKS_PER_DITCH = 3
# Attempts at laying out one task before the draw is given up.
_TASK_ATTEMPTS = 12
# Flat ground between the approach zone and the fence (m), and the fence's overlap past a corner.
_FENCE_GAP_M = 3.0
# A sine's tightest bend keeps at least this multiple of the family's bend limit.
SINE_BEND_MARGIN = 1.2
# A crater's tasks cross at most this far from square to its dividing walls (deg).
CRATER_MAX_CROSSING_DEG = 10.0
# Steps, and the tolerance (m), in laying a start or goal the drawn approach beyond the edge.
_EDGE_STEPS = 20
_EDGE_TOLERANCE_M = 0.01
# How far an end wall reaches into the ditch's rounded end (the packaged walled ditches' 1 m).
_WALL_INTO_SLOPE_M = 1.0
# Steep wall (m) kept between two windows of one wall, so that they stay two windows.
WINDOW_GAP_M = 2.0


@dataclass
class SampledDitch:
    """One generated ditch.

    Attributes:
        seed: the seed asked for.
        draw: the draw kept (0: the first; k: the first k draws could not be built or laid out).
        name: the environment's name, `ditch_<seed>`.
        environment: the fenced terrain and its three tasks.
    """

    seed: int
    draw: int
    name: str
    environment: Environment


def ditch_name(seed: int) -> str:
    return f"ditch_{seed:04d}"


def sample_ditch(seed: int, ranges: BenchmarkRanges | None = None) -> SampledDitch:
    """The ditch of `seed` (see the module docstring).

    Raises:
        ConfigError: a negative seed, ranges out of bounds, or no buildable draw in `MAX_DRAWS`
            (the message names the seed and the last draw's reason).
    """
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed={seed!r} must be a non-negative integer")
    ranges = ranges or BenchmarkRanges()
    ranges.validate()
    reason = ""
    for draw in range(MAX_DRAWS):
        rng = np.random.default_rng([int(seed), draw])
        try:
            environment = _draw_environment(rng, ranges)
            environment.description = f"procedural ditch: seed {seed}, draw {draw}; " + environment.description
            validate_environment(environment)
        except (TerrainError, ConfigError) as error:
            reason = str(error)
            continue
        return SampledDitch(int(seed), draw, ditch_name(int(seed)), environment)
    raise ConfigError(f"seed {seed}: none of {MAX_DRAWS} draws gives a ditch the family can build and fence "
                      f"(the last: {reason}); widen the ranges or use another seed")


def _uniform(rng: np.random.Generator, interval) -> float:
    low, high = interval
    return round(float(rng.uniform(low, high)), 3)  # mm and millidegrees: a readable ditches file


def _draw_terrain(rng: np.random.Generator, ranges: BenchmarkRanges) -> TerrainParams:
    kind = ranges.course_kinds[int(rng.integers(len(ranges.course_kinds)))]
    hinge = _uniform(rng, ranges.hinge_radius_m)
    params = TerrainParams(course=kind, slope_deg=_uniform(rng, ranges.slope_deg), depth_m=_uniform(rng, ranges.depth_m),
                           hinge_radius_m=hinge, toe_radius_m=hinge,
                           field_margin_m=ranges.approach_m[1] + _FENCE_GAP_M + 2.0)
    if kind == "point":
        params.bottom_width_m = _uniform(rng, ranges.crater_diameter_m)
        return params
    params.bottom_width_m = _uniform(rng, ranges.bottom_width_m)
    params.length_m = _uniform(rng, ranges.course_length_m)
    if kind == "sine":
        params.sine_wavelength_m = _uniform(rng, ranges.sine_wavelength_m)
        # The amplitude is drawn below the one whose apex bends at the family's limit (with a
        # margin: near the limit the collision geometry's inner side is centimetres off), so
        # that sines are not redrawn as other kinds more often than the rest.
        k = 2 * math.pi / params.sine_wavelength_m
        highest = 1.0 / (SINE_BEND_MARGIN * min_bend_radius_m(params) * k**2)
        low, high = ranges.sine_amplitude_m
        params.sine_amplitude_m = _uniform(rng, [low, max(low, min(high, highest))])
    elif kind == "arc":
        params.arc_radius_m = _uniform(rng, ranges.arc_radius_m)
        # Rounded down to the mm, so that the shortened arc's sweep stays within the limit.
        longest = math.floor(math.radians(ranges.arc_max_sweep_deg) * params.arc_radius_m * 1000.0) / 1000.0
        params.length_m = min(params.length_m, longest)
    return params


def _draw_window_slopes(rng: np.random.Generator, windows: WindowRanges) -> dict[str, list[float]]:
    """Each wall's windows' slopes (deg), as many as its drawn count."""
    low, high = windows.per_wall
    return {side: [_uniform(rng, windows.slope_deg) for _ in range(int(rng.integers(low, high + 1)))]
            for side in WALL_SIDES}


def _draw_environment(rng: np.random.Generator, ranges: BenchmarkRanges) -> Environment:
    params = _draw_terrain(rng, ranges)
    window_slopes = _draw_window_slopes(rng, ranges.windows) if ranges.windows else None
    # The field and the tasks are laid out on the ditch at its widest: with windows, the
    # gentlest window's slope all along (its hinge is the windowed ditch's edge).
    layout = params if window_slopes is None else replace(
        params, slope_deg=min(slope for slopes in window_slopes.values() for slope in slopes))
    terrain = DitchTerrain(layout)
    reach = terrain.half_width_m + ranges.approach_m[1] + _FENCE_GAP_M
    low, high = terrain.course_xy.min(axis=0) - reach, terrain.course_xy.max(axis=0) + reach
    corners = [[low[0], low[1]], [high[0], low[1]], [high[0], high[1]], [low[0], high[1]], [low[0], low[1]]]
    walls = [Wall(points=[[round(float(v), 3) for v in corner] for corner in corners])]
    if params.course == "point":
        walls += _crater_walls(rng, terrain, low, high)
    else:
        # With windows the rounded ends are steep: the end walls seal against the steep slope.
        walls += _end_walls(terrain if window_slopes is None else DitchTerrain(params), low, high)
    params.walls = layout.walls = walls
    terrain = DitchTerrain(layout)
    tasks = [_draw_task(rng, ranges, terrain, index, low, high) for index in range(TASKS_PER_DITCH)]
    description = (f"{params.course}, slope {params.slope_deg:.1f} deg, bottom {params.bottom_width_m:.2f} m, "
                   f"depth {params.depth_m:.2f} m")
    if window_slopes is not None:
        params.wall_slopes = _place_windows(rng, ranges.windows, window_slopes, params.slope_deg, terrain, tasks)
        description += "; windows " + "; ".join(
            f"{side} " + ", ".join(f"{s.from_m:.1f}-{s.to_m:.1f} m at {s.slope_deg:.1f} deg"
                                   for s in getattr(params.wall_slopes, side) if s.slope_deg != params.slope_deg)
            for side in WALL_SIDES)
    return Environment(description=description, terrain=params, tasks=tasks)


def _place_windows(rng: np.random.Generator, windows: WindowRanges, window_slopes: dict[str, list[float]],
                   steep_deg: float, terrain: DitchTerrain, tasks: list[Task]) -> WallSlopes:
    """Each wall's sections: its windows at drawn widths and places (see the module docstring),
    steep wall (`steep_deg`) between them. `terrain`: the straight ditch at its widest.

    Raises:
        ConfigError: no place left on a wall for a window of the narrowest width.
    """
    length = terrain.params.length_m
    wall_slopes = WallSlopes()
    for side in WALL_SIDES:
        taken = [_line_band(terrain, task, side, windows.line_margin_m) for task in tasks]
        placed = []
        for slope in window_slopes[side]:
            runs = _free_runs(windows.end_margin_m, length - windows.end_margin_m, taken)
            # Drawn below the widest that fits (as a sine's amplitude is), so that a wide draw is
            # not redrawn as a whole new ditch.
            widest = math.floor(max((b - a for a, b in runs), default=0.0) * 1000.0) / 1000.0
            if widest < windows.width_m[0]:
                raise ConfigError(f"wall_slopes.{side}: no place for a {windows.width_m[0]:g} m window "
                                  f"{windows.end_margin_m:g} m from the ends, {windows.line_margin_m:g} m from the "
                                  f"tasks' lines and {WINDOW_GAP_M:g} m from the wall's other windows")
            width = _uniform(rng, [windows.width_m[0], min(windows.width_m[1], widest)])
            begin = _draw_place(rng, width, runs)
            end = round(begin + width, 3)
            placed.append(SlopeSection(begin, end, slope))
            taken.append((begin - WINDOW_GAP_M, end + WINDOW_GAP_M))
        sections, reached = [], 0.0
        for window in sorted(placed, key=lambda section: section.from_m):
            sections += [SlopeSection(reached, window.from_m, steep_deg), window]
            reached = window.to_m
        setattr(wall_slopes, side, [*sections, SlopeSection(reached, length, steep_deg)])
    return wall_slopes


def _line_band(terrain: DitchTerrain, task: Task, side: str, margin_m: float) -> tuple[float, float]:
    """Where along a straight course (m from its start) a task's straight line from start to
    goal crosses the wall on `side`, between the toe and the hinge, widened by `margin_m`."""
    (x0, y0), (x1, y1) = task.start[:2], task.goal
    sign = -1.0 if side == "right" else 1.0
    along = [x0 + (x1 - x0) * (sign * distance - y0) / (y1 - y0) + terrain.params.length_m / 2
             for distance in (terrain.toe_distance_m, terrain.hinge_distance_m)]
    return min(along) - margin_m, max(along) + margin_m


def _free_runs(low: float, high: float, taken: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The stretches of [low, high] off every `taken` interval."""
    runs = [(low, high)]
    for start, stop in taken:
        runs = [run for a, b in runs for run in ((a, min(b, start)), (max(a, stop), b)) if run[0] < run[1]]
    return runs


def _draw_place(rng: np.random.Generator, width: float, runs: list[tuple[float, float]]) -> float:
    """A window's beginning (m, to the mm), uniform over those that keep [begin, begin + width]
    within one of `runs` (one at least as long as `width`)."""
    starts = [(a, b - width) for a, b in runs if b - a >= width]
    offset = float(rng.uniform(0.0, sum(b - a for a, b in starts)))
    for a, b in starts:
        if offset <= b - a:
            return round(a + offset, 3)
        offset -= b - a
    return round(starts[-1][1], 3)


def _ray_to_box(origin: np.ndarray, direction: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    """Distance along `direction` (unit) from `origin` (inside the box) to the box's boundary."""
    with np.errstate(divide="ignore"):
        steps = np.where(direction > 0, (high - origin) / direction,
                         np.where(direction < 0, (low - origin) / direction, np.inf))
    return float(np.min(steps))


def _wall_along(start, direction, low, high) -> Wall:
    """A wall from `start` along `direction` to just past the fence."""
    end = start + direction * (_ray_to_box(start, direction, low, high) + 0.1)
    return Wall(points=[[round(float(v), 3) for v in start], [round(float(v), 3) for v in end]])


def _end_walls(terrain: DitchTerrain, low, high) -> list[Wall]:
    """A wall from each end of the course, along its last heading, to the fence."""
    course = terrain.course_xy
    walls = []
    for end, before in ((course[-1], course[-2]), (course[0], course[1])):
        direction = (end - before) / np.linalg.norm(end - before)
        start = end + direction * (terrain.hinge_distance_m - _WALL_INTO_SLOPE_M)
        walls.append(_wall_along(start, direction, low, high))
    return walls


def _crater_walls(rng, terrain: DitchTerrain, low, high) -> list[Wall]:
    """A wall on each side of the crater along a drawn direction, from the rim to the fence:
    the tasks cross the crater from one side of that line to the other."""
    angle = float(rng.uniform(0.0, math.pi))
    direction = np.array([math.cos(angle), math.sin(angle)])
    rim = terrain.hinge_distance_m - _WALL_INTO_SLOPE_M
    return [_wall_along(sign * rim * direction, sign * direction, low, high) for sign in (1.0, -1.0)]


def _crossing_frame(terrain: DitchTerrain, index: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Where task `index` crosses the course, and the course's unit normal there."""
    if terrain.params.course == "point":
        starts, ends, _ = terrain.wall_segments()
        along = ends[-1] - starts[-1]  # The crater's dividing walls run along this direction.
        along /= np.linalg.norm(along)
        normal = np.array([-along[1], along[0]])
        offset = ((index - 1) * 0.1 + rng.uniform(-0.05, 0.05)) * terrain.toe_distance_m
        return offset * along, normal
    course = terrain.course_xy
    lengths = np.linalg.norm(np.diff(course, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    fraction = 0.3 + (0.4 / TASKS_PER_DITCH) * (index + rng.uniform(0.0, 1.0))
    position = fraction * arc[-1]
    segment = min(int(np.searchsorted(arc, position, side="right")) - 1, len(lengths) - 1)
    tangent = (course[segment + 1] - course[segment]) / lengths[segment]
    point = course[segment] + tangent * (position - arc[segment])
    return point, np.array([-tangent[1], tangent[0]])


def _draw_task(rng, ranges: BenchmarkRanges, terrain: DitchTerrain, index: int, low, high) -> Task:
    reason = ""
    for _ in range(_TASK_ATTEMPTS):
        point, normal = _crossing_frame(terrain, index, rng)
        angle = math.radians(_uniform(rng, ranges.crossing_angle_deg)) * (1.0 if rng.random() < 0.5 else -1.0)
        if terrain.params.course == "point":
            # A crossing that runs along the rim meets the crater's dividing walls unless it
            # starts well away from them (train split: the expert hit them in 8 of 45 crossings
            # turned up to 35 deg from square).
            angle = float(np.clip(angle, -math.radians(CRATER_MAX_CROSSING_DEG), math.radians(CRATER_MAX_CROSSING_DEG)))
        side = 1.0 if rng.random() < 0.5 else -1.0
        c, s = math.cos(angle), math.sin(angle)
        direction = side * np.array([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1]])
        approach_m = _uniform(rng, ranges.approach_m)
        reach = (terrain.hinge_distance_m + approach_m) / max(c, 0.5)
        start = _beyond_edge(terrain, point, -direction, reach, approach_m)
        goal = _beyond_edge(terrain, point, direction, reach, approach_m)
        reason = _task_problem(terrain, start, goal, low, high, approach_m)
        if not reason:
            yaw = math.degrees(math.atan2(direction[1], direction[0]))
            return Task(name=f"crossing_{index}", start=[*(round(float(v), 3) for v in start), round(yaw, 2)],
                        goal=[round(float(v), 3) for v in goal])
    raise ConfigError(f"task {index}: no layout fits ({reason})")


def _beyond_edge(terrain: DitchTerrain, point, direction, reach: float, approach_m: float) -> np.ndarray:
    """The point `reach` or further along `direction` from the course point `point` that lies
    `approach_m` beyond the ditch's edge. The straight line ends there on a line course; on a
    curved one the course can bend back toward it (inside an arc, past a sine's apex), so the
    line goes on by what is missing until it is that far from every part of the course."""
    for _ in range(_EDGE_STEPS):
        xy = point + reach * direction
        missing = approach_m - float(terrain.beyond_edge_m(xy))
        if missing <= _EDGE_TOLERANCE_M:
            break
        reach += missing
    return xy


def _task_problem(terrain: DitchTerrain, start, goal, low, high, approach_m: float) -> str:
    """Why a start/goal pair does not fit ("" when it does)."""
    for label, xy in (("start", start), ("goal", goal)):
        margin = TASK_CLEARANCE_M + 0.5
        if np.any(xy < low + margin) or np.any(xy > high - margin):
            return f"the {label} falls outside the fence"
        beyond_edge_m = float(terrain.beyond_edge_m(xy))
        if beyond_edge_m < approach_m - 2 * _EDGE_TOLERANCE_M:
            return f"the {label} lies {beyond_edge_m:.2f} m beyond the ditch's edge, short of the drawn {approach_m} m"
        if float(terrain.distance_to_walls(xy)) < margin:
            return f"the {label} is too near a wall"
    return ""
