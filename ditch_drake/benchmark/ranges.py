"""The ranges the procedural ditch generator draws from, as data (`ranges.yaml`).

A `BenchmarkRanges` is read with `yaml_load_typed`; every `[low, high]` must be ordered and
lie inside `LIMITS` (the terrain family's and the task layout's reach), and an arc's radius may
not bend tighter than the family builds for the widest ditch the ranges draw
(`terrain.min_bend_radius_m`), else a ConfigError names the key, the value and what is allowed.
"""

import itertools
import math
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path

from ditch_drake.common.config_yaml import load_typed_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.world.terrain import TerrainParams, min_bend_radius_m

# The course kinds the generator lays out (each a `TerrainParams.course`).
GENERATED_COURSE_KINDS = ("line", "sine", "arc", "point")

# Where each range may lie: [allowed low, allowed high].
LIMITS = {
    "slope_deg": (20.0, 70.0),
    "bottom_width_m": (1.0, 12.0),
    "depth_m": (1.0, 6.0),
    "hinge_radius_m": (0.0, 1.5),
    "course_length_m": (15.0, 60.0),
    "sine_amplitude_m": (0.0, 10.0),
    "sine_wavelength_m": (10.0, 80.0),
    "arc_radius_m": (5.0, 100.0),
    "crater_diameter_m": (2.0, 20.0),
    "crossing_angle_deg": (0.0, 60.0),
    "approach_m": (3.0, 15.0),
    "arc_max_sweep_deg": (30.0, 180.0),  # a number, not a range; a half circle at most (TerrainParams)
}


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

    def validate(self) -> None:
        """Raises ConfigError naming the first key out of bounds, inverted, or unknown, or an
        arc radius tighter than the family's bend limit."""
        if not self.course_kinds:
            raise ConfigError(f"ranges: course_kinds=[] is empty: expected some of {list(GENERATED_COURSE_KINDS)}")
        for kind in self.course_kinds:
            if kind not in GENERATED_COURSE_KINDS:
                raise ConfigError(f"ranges: course_kinds has {kind!r}: expected some of {list(GENERATED_COURSE_KINDS)}")
        for item in fields(self):
            if item.name in ("course_kinds", "arc_max_sweep_deg"):
                continue
            value = getattr(self, item.name)
            allowed_low, allowed_high = LIMITS[item.name]
            allowed = f"[low, high] with {allowed_low:g} <= low <= high <= {allowed_high:g}"
            if (len(value) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value)):
                raise ConfigError(f"ranges: {item.name}={value!r} is not a range: expected {allowed}")
            low, high = value
            if low > high:
                raise ConfigError(f"ranges: {item.name}={value!r} is inverted: expected {allowed}")
            if low < allowed_low or high > allowed_high:
                raise ConfigError(f"ranges: {item.name}={value!r} is out of bounds: expected {allowed}")
        sweep_low, sweep_high = LIMITS["arc_max_sweep_deg"]
        sweep = self.arc_max_sweep_deg
        if not (isinstance(sweep, (int, float)) and math.isfinite(sweep) and sweep_low <= sweep <= sweep_high):
            raise ConfigError(f"ranges: arc_max_sweep_deg={sweep!r} is out of bounds: expected a number in "
                              f"[{sweep_low:g}, {sweep_high:g}]")
        if "arc" in self.course_kinds:
            limit = self.widest_arc_bend_limit_m()
            if self.arc_radius_m[0] < limit:
                raise ConfigError(f"ranges: arc_radius_m={self.arc_radius_m!r} bends tighter than the terrain family "
                                  f"builds: expected a low end of at least {limit:.2f} m, min_bend_radius_m of the "
                                  "widest ditch these ranges draw (raise it, or narrow bottom_width_m, depth_m, "
                                  "hinge_radius_m or steepen slope_deg)")

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
