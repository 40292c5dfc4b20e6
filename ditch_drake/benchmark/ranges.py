"""The ranges the procedural ditch generator draws from, as data (`ranges.yaml`).

A `BenchmarkRanges` is read with `yaml_load_typed`; every `[low, high]` must be ordered and
lie inside `LIMITS` (the terrain family's and the task layout's reach), and an arc's radius may
not bend tighter than the family builds for the widest ditch the ranges draw
(`terrain.min_bend_radius_m`), else a ConfigError names the key, the value and what is allowed.

Ranges with `windows` (`WindowRanges`, the search split's `search_ranges.yaml`) draw straight
ditches whose walls are too steep to stand on at any heading except in one or more windows
each (`TerrainParams.wall_slopes`): `slope_deg` is then the steep walls' slope, and must lie
past `all_headings_tip_angle_deg`.
"""

import itertools
import math
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path

from ditch_drake.common.config_yaml import load_typed_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.spec import robot
from ditch_drake.world.ingress import smallest_tip_angle_deg
from ditch_drake.world.terrain import TerrainParams, min_bend_radius_m

# The course kinds the generator lays out (each a `TerrainParams.course`).
GENERATED_COURSE_KINDS = ("line", "sine", "arc", "point")

# Where each range may lie: [allowed low, allowed high].
LIMITS = {
    "slope_deg": (20.0, 70.0),
    "bottom_width_m": (1.0, 12.0),
    "depth_m": (1.0, 6.0),
    "hinge_radius_m": (0.0, 1.5),
    "course_length_m": (15.0, 80.0),  # the search split's windowed ditches are up to 70 m long
    "sine_amplitude_m": (0.0, 10.0),
    "sine_wavelength_m": (10.0, 80.0),
    "arc_radius_m": (5.0, 100.0),
    "crater_diameter_m": (2.0, 20.0),
    "crossing_angle_deg": (0.0, 60.0),
    "approach_m": (3.0, 15.0),
    "arc_max_sweep_deg": (30.0, 180.0),  # a number, not a range; a half circle at most (TerrainParams)
}


def all_headings_tip_angle_deg() -> float:
    """The slope (deg) past which the robot tips at every heading: toward a corner of its wheel
    rectangle, tan^2 s = tan^2(fore-aft tip angle) + tan^2(sideways tip angle), 68.3 deg
    (docs/concepts/terrain_family.md, "Ways in and out")."""
    return math.degrees(math.atan(math.hypot(math.tan(robot.tip_angle_fore_aft_rad()),
                                             math.tan(robot.tip_angle_sideways_rad()))))


# Where `slope_deg` may lie in ranges with windows: the walls outside the windows tip the robot
# at every heading (68.3 deg, rounded up) and stay short of vertical.
WINDOWED_SLOPE_LIMITS = (math.ceil(all_headings_tip_angle_deg() * 10) / 10, 80.0)

# Where each window range may lie (`WindowRanges`).
WINDOW_LIMITS = {
    "per_wall": (1, 3),
    # Never narrower than the robot; the ways-in-and-out proof needs somewhat more (a step
    # where a wall changes slope closes a strip on each side), and a draw it refuses is redrawn.
    "width_m": (float(robot.CHASSIS_SIZE_M[1]), 40.0),
    "slope_deg": (20.0, math.floor(smallest_tip_angle_deg() * 10) / 10),
    "end_margin_m": (1.0, 20.0),  # numbers, not ranges
    "line_margin_m": (0.0, 10.0),
}


@dataclass
class WindowRanges:
    """Windows in a straight ditch's steep walls: where the robot can go down and climb out.

    Each wall (right and left of the course) gets its own windows, at drawn places along the
    course; everywhere else it stands at the ranges' `slope_deg` (steep past every heading).
    The windows keep `end_margin_m` from the course's ends (the rounded ends stay steep, and
    the walls from the ends to the fence seal against them) and `line_margin_m` from where
    each task's straight line from start to goal crosses the wall, so that a controller that
    ignores the windows drives into a steep section; and at least 2 m of steep wall between
    two windows of one wall (`generator.WINDOW_GAP_M`). A draw without room for its windows is
    redrawn.

    Attributes:
        per_wall: how many windows each wall has, an integer drawn in [low, high].
        width_m: a window's length along the course.
        slope_deg: a window's wall angle, no steeper than the robot's smallest tip-over angle
            (`ingress.smallest_tip_angle_deg`, 59.6 deg).
        end_margin_m: a number: steep wall kept at each end of the course.
        line_margin_m: a number: steep wall kept each side of a task's straight line.
    """

    per_wall: list[int] = field(default_factory=lambda: [1, 2])
    width_m: list[float] = field(default_factory=lambda: [8.0, 20.0])
    slope_deg: list[float] = field(default_factory=lambda: [45.0, 55.0])
    end_margin_m: float = 5.0
    line_margin_m: float = 3.0

    def validate(self) -> None:
        """Raises ConfigError naming the first key (`windows.<key>`) out of bounds or inverted."""
        why = {"width_m": " (no narrower than the robot)", "slope_deg": " (no steeper than the robot's smallest "
               "tip-over angle: crossable at every heading)"}
        for name in ("per_wall", "width_m", "slope_deg"):
            _check_range(f"windows.{name}", getattr(self, name), WINDOW_LIMITS[name], integer=name == "per_wall",
                         why=why.get(name, ""))
        for name in ("end_margin_m", "line_margin_m"):
            _check_number(f"windows.{name}", getattr(self, name), WINDOW_LIMITS[name])


def _check_range(key: str, value, limits: tuple[float, float], integer: bool = False, why: str = "") -> None:
    """Raises ConfigError unless `value` is [low, high], ordered, within `limits` (`why`: what
    the limits are for, appended to the message)."""
    allowed_low, allowed_high = limits
    kind = " of integers" if integer else ""
    allowed = f"[low, high]{kind} with {allowed_low:g} <= low <= high <= {allowed_high:g}{why}"
    number = int if integer else (int, float)
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, number) and math.isfinite(v) for v in value)):
        raise ConfigError(f"ranges: {key}={value!r} is not a range: expected {allowed}")
    low, high = value
    if low > high:
        raise ConfigError(f"ranges: {key}={value!r} is inverted: expected {allowed}")
    if low < allowed_low or high > allowed_high:
        raise ConfigError(f"ranges: {key}={value!r} is out of bounds: expected {allowed}")


def _check_number(key: str, value, limits: tuple[float, float]) -> None:
    """Raises ConfigError unless `value` is a finite number within `limits`."""
    allowed_low, allowed_high = limits
    if not (isinstance(value, (int, float)) and math.isfinite(value) and allowed_low <= value <= allowed_high):
        raise ConfigError(f"ranges: {key}={value!r} is out of bounds: expected a number in "
                          f"[{allowed_low:g}, {allowed_high:g}]")


@dataclass
class BenchmarkRanges:
    """What the generator draws, uniformly within each [low, high] (m, deg).

    Attributes:
        course_kinds: the course kinds to draw from, equally likely: "line" (straight),
            "sine", "arc" (a circular arc) and "point" (a round crater).
        slope_deg: the walls' angle from horizontal.
        bottom_width_m: the flat bottom's width (line, sine, arc).
        depth_m: depth below the surrounding ground.
        hinge_radius_m: rounding of the top edge (the toe's rounding is the same).
        course_length_m: length of the course (line, sine along x, arc along the arc).
        sine_amplitude_m, sine_wavelength_m: the sine's; a draw bending tighter than the
            family allows (`terrain.min_bend_radius_m`) is redrawn.
        arc_radius_m: the arc's radius of curvature. Its low end may not bend tighter than
            the family builds (`terrain.min_bend_radius_m`) the widest ditch these ranges draw
            (widest bottom, deepest, shallowest wall, largest hinge radius).
        arc_max_sweep_deg: a number, not a range: an arc's longest sweep (length / radius);
            longer arcs are shortened to it. Inside a tight arc that sweeps far, a task's line
            meets the course again before its approach fits, so tight arcs need short sweeps.
        crater_diameter_m: a crater's flat-bottom diameter.
        crossing_angle_deg: how far each task's straight line from start to goal turns
            away from the course's normal where it crosses (0: square across).
        approach_m: flat ground between the ditch's edge and each task's start and goal.
        windows: None, or the walls' windows (`WindowRanges`): then the course is a line,
            `slope_deg` is the walls' slope outside the windows, past every heading's tip-over
            angle (`all_headings_tip_angle_deg`, 68.3 deg), and the course is long enough for
            the widest window between its end margins.
    """

    course_kinds: list[str] = field(default_factory=lambda: list(GENERATED_COURSE_KINDS))
    slope_deg: list[float] = field(default_factory=lambda: [45.0, 55.0])
    bottom_width_m: list[float] = field(default_factory=lambda: [2.0, 8.0])
    depth_m: list[float] = field(default_factory=lambda: [3.0, 5.0])
    hinge_radius_m: list[float] = field(default_factory=lambda: [0.3, 0.7])
    course_length_m: list[float] = field(default_factory=lambda: [26.0, 36.0])
    sine_amplitude_m: list[float] = field(default_factory=lambda: [1.0, 5.0])
    sine_wavelength_m: list[float] = field(default_factory=lambda: [20.0, 40.0])
    arc_radius_m: list[float] = field(default_factory=lambda: [12.0, 30.0])
    crater_diameter_m: list[float] = field(default_factory=lambda: [10.0, 12.0])
    crossing_angle_deg: list[float] = field(default_factory=lambda: [0.0, 35.0])
    approach_m: list[float] = field(default_factory=lambda: [5.0, 8.0])
    arc_max_sweep_deg: float = 180.0
    windows: WindowRanges | None = None

    def validate(self) -> None:
        """Raises ConfigError naming the first key out of bounds, inverted, or unknown, or an
        arc radius tighter than the family's bend limit."""
        if not self.course_kinds:
            raise ConfigError(f"ranges: course_kinds=[] is empty: expected some of {list(GENERATED_COURSE_KINDS)}")
        for kind in self.course_kinds:
            if kind not in GENERATED_COURSE_KINDS:
                raise ConfigError(f"ranges: course_kinds has {kind!r}: expected some of {list(GENERATED_COURSE_KINDS)}")
        limits, why = dict(LIMITS), {}
        if self.windows is not None:
            limits["slope_deg"] = WINDOWED_SLOPE_LIMITS
            why["slope_deg"] = (" (with windows, the walls outside them: steep enough to tip the robot at every "
                                "heading)")
        for item in fields(self):
            if item.name in ("course_kinds", "arc_max_sweep_deg", "windows"):
                continue
            _check_range(item.name, getattr(self, item.name), limits[item.name], why=why.get(item.name, ""))
        _check_number("arc_max_sweep_deg", self.arc_max_sweep_deg, LIMITS["arc_max_sweep_deg"])
        if self.windows is not None:
            self._validate_windows()
        if "arc" in self.course_kinds:
            limit = self.widest_arc_bend_limit_m()
            if self.arc_radius_m[0] < limit:
                raise ConfigError(f"ranges: arc_radius_m={self.arc_radius_m!r} bends tighter than the terrain family "
                                  f"builds: expected a low end of at least {limit:.2f} m, min_bend_radius_m of the "
                                  "widest ditch these ranges draw (raise it, or narrow bottom_width_m, depth_m, "
                                  "hinge_radius_m or steepen slope_deg)")

    def _validate_windows(self) -> None:
        """Raises ConfigError unless windowed ranges draw straight ditches long enough for the
        widest window between the end margins."""
        windows = self.windows
        windows.validate()
        if self.course_kinds != ["line"]:
            raise ConfigError(f"ranges: course_kinds={self.course_kinds!r} with windows: expected [line] (walls whose "
                              "slope varies are built on a straight ditch only)")
        shortest = 2 * windows.end_margin_m + windows.width_m[1]
        if self.course_length_m[0] < shortest:
            raise ConfigError(f"ranges: course_length_m={self.course_length_m!r} is too short for the windows: "
                              f"expected a low end of at least {shortest:g} m (2 x windows.end_margin_m + the "
                              "widest windows.width_m)")

    def widest_arc_bend_limit_m(self) -> float:
        """The family's bend limit (`terrain.min_bend_radius_m`, m) for the widest arc these
        ranges draw: the largest over the corners of the bottom, depth, slope and hinge radius
        ranges (the generator rounds the toe as the hinge)."""
        return max(min_bend_radius_m(TerrainParams(course="arc", bottom_width_m=bottom, depth_m=depth,
                                                   slope_deg=slope, hinge_radius_m=hinge, toe_radius_m=hinge))
                   for bottom, depth, slope, hinge in itertools.product(
                       self.bottom_width_m, self.depth_m, self.slope_deg, self.hinge_radius_m))


def packaged_ranges_path(name: str = "ranges.yaml") -> Path:
    """A ranges file shipped in `ditch_drake/benchmark` (the benchmark's by default)."""
    return Path(str(resources.files("ditch_drake.benchmark") / name))


def load_ranges(path: str | Path | None = None) -> BenchmarkRanges:
    """The ranges of a YAML file (the packaged `ranges.yaml` by default), validated.

    Raises:
        ConfigError: unreadable, unknown keys, wrong types, or a range out of bounds or inverted.
    """
    ranges = load_typed_yaml(path or packaged_ranges_path(), BenchmarkRanges, "benchmark ranges")
    ranges.validate()
    return ranges
