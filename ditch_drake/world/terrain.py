"""One parametric family of negative-obstacle terrain (docs/design.md, "The ditches").

A ditch is everything within some distance of a *course*: a polyline in the ground
plane (a straight line, a sine, or a single point for a round crater). The terrain
height depends only on the planar distance d to the course, through a
cross-section profile: a flat bottom for d <= bottom half-width, a rounded toe, a
straight wall at the slope angle, a rounded hinge, and flat ground beyond.

The same description gives
- analytic queries (height, surface normal, distance and direction to the course,
  edge lines) for drivers, tests and analysis, and
- collision and visual geometry: rotated `Box` pieces swept along the course
  segments and revolved around its bends and ends, a floor box, and flat-ground
  boxes. Boxes under point contact are exact and fast; a terrain `Mesh` would
  collide as its convex hull (docs/concepts/physics.md), so a winding ditch's collision geometry
  joins each section's wall, hinge and flat edge, whose solid is convex, into one
  `Convex` (`ConvexPiece`).

A straight ditch's two walls may each change slope along the course
(`TerrainParams.wall_slopes`: sections of the wall's length, each at its own slope), so that
it can be crossed only where a wall is gentle enough (docs/concepts/terrain_family.md,
"Walls whose slope varies"); between two sections the wall steps from one profile to the other.

A ditch may also be fenced: `TerrainParams.walls` are straight wall segments on the
ground (tall boxes, collision and visual geometry), so that every route from a start to
its goal has to cross the ditch (`ditch_drake.world.bypass` proves it for each task).

A new shape is a new `TerrainParams`, not new code.
"""

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull

from ditch_drake.common.errors import TerrainError

COURSE_KINDS = ("line", "sine", "point", "arc")
# The ditch's two walls, named by the side of the course they stand on, facing along it.
WALL_SIDES = ("right", "left")
# How far two sections' ends may miss each other or the course's ends (m) and still meet.
SECTION_TOLERANCE_M = 1e-6


@dataclass
class Wall:
    """A fence of straight wall segments standing on the ground (m).

    Attributes:
        points: the wall's centre line [[x, y], ...], at least two points. It may reach
            into the ditch's sloping sides to seal against them, never over its floor.
        height_m: how far it stands above the flat ground (z = 0); it reaches down to the
            ditch's floor level, so it stands out of the slopes it enters too.
        thickness_m: its width across the centre line.
    """

    points: list[list[float]] = field(default_factory=list)
    height_m: float = 1.0
    thickness_m: float = 0.2


@dataclass
class SlopeSection:
    """One stretch of a ditch's wall at one slope.

    Attributes:
        from_m: where it begins, along the course from the course's start (m).
        to_m: where it ends (m); the next section begins here.
        slope_deg: the wall's angle from horizontal along the stretch, in (0, 90).
    """

    from_m: float = 0.0
    to_m: float = 0.0
    slope_deg: float = 55.0


@dataclass
class WallSlopes:
    """The slopes of a straight ditch's two walls along the course, each wall on its own.

    Positions run along the course from its start (x = -length_m / 2) to its end (x =
    length_m / 2). A wall's sections follow each other without gap or overlap and cover its
    whole length, [0, length_m]; each rounded end of the ditch takes the slopes of the
    sections that end there. Between two sections of different slopes the wall steps from
    one profile to the other (docs/concepts/terrain_family.md).

    Attributes:
        right: the wall on the course's right facing along it (y < 0): the wall a task that
            starts at y < 0 goes down, and one that ends there climbs. Empty: `slope_deg`
            all along.
        left: the wall on its left (y > 0). Empty: `slope_deg` all along.
    """

    right: list[SlopeSection] = field(default_factory=list)
    left: list[SlopeSection] = field(default_factory=list)


@dataclass
class TerrainParams:
    """Parameters of one ditch (lengths in m, angles in degrees).

    Attributes:
        course: "line" (straight ditch along x), "sine" (course y = A sin(2 pi x / L_w)),
            "point" (a round crater centred on the origin) or "arc" (a circular arc of
            radius arc_radius_m, its midpoint at the origin heading +x, bending toward +y).
            A sine's or an arc's tightest bend radius must be at least
            `min_bend_radius_m` (docs/concepts/terrain_family.md).
        length_m: length of the course along x ("line" and "sine"), its arc length ("arc").
        sine_amplitude_m: A, for "sine".
        sine_wavelength_m: L_w, for "sine".
        bottom_width_m: width of the flat bottom (the crater's bottom diameter).
        depth_m: depth below the surrounding ground.
        slope_deg: wall angle from horizontal (of both walls all along, unless `wall_slopes`
            says otherwise).
        hinge_radius_m: rounding radius of the top edge (the hinge line).
        toe_radius_m: rounding radius of the bottom edge.
        arc_facets: flat facets per rounded edge in the collision geometry.
        max_turn_deg: largest heading change between course segments, and the
            angular width of the pieces revolved around bends and ends.
        arc_radius_m: the arc's radius, for "arc" (its sweep length_m / arc_radius_m is at
            most pi: 180 degrees).
        field_margin_m: flat ground kept around the ditch's outer edge.
        walls: fences on the ground (none: an open field).
        wall_slopes: slopes that vary along a "line" course, each wall on its own (none: both
            walls at `slope_deg` all along).
    """

    course: str = "line"
    length_m: float = 30.0
    sine_amplitude_m: float = 0.0
    sine_wavelength_m: float = 30.0
    bottom_width_m: float = 4.0
    depth_m: float = 4.0
    slope_deg: float = 55.0
    hinge_radius_m: float = 0.5
    toe_radius_m: float = 0.5
    arc_facets: int = 4
    max_turn_deg: float = 6.0
    arc_radius_m: float = 15.0
    field_margin_m: float = 20.0
    walls: list[Wall] = field(default_factory=list)
    wall_slopes: WallSlopes = field(default_factory=WallSlopes)

    def validate(self) -> None:
        """Raises TerrainError naming the first parameter out of range."""

        def fail(name, value, allowed):
            raise TerrainError(f"terrain parameter {name}={value!r} is out of range: expected {allowed}")

        if self.course not in COURSE_KINDS:
            fail("course", self.course, f"one of {COURSE_KINDS}")
        for name in ("length_m", "sine_amplitude_m", "sine_wavelength_m", "bottom_width_m", "depth_m",
                     "slope_deg", "hinge_radius_m", "toe_radius_m", "max_turn_deg", "field_margin_m",
                     "arc_radius_m"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                fail(name, value, "a finite number")
        if not 0.0 < self.slope_deg < 90.0:
            fail("slope_deg", self.slope_deg, "0 < slope_deg < 90")
        if self.depth_m <= 0.0:
            fail("depth_m", self.depth_m, "depth_m > 0")
        if self.bottom_width_m < 0.0:
            fail("bottom_width_m", self.bottom_width_m, "bottom_width_m >= 0")
        if self.course == "point" and self.bottom_width_m <= 0.0:
            fail("bottom_width_m", self.bottom_width_m, "bottom_width_m > 0 for a crater")
        if self.hinge_radius_m < 0.0:
            fail("hinge_radius_m", self.hinge_radius_m, "hinge_radius_m >= 0")
        if self.toe_radius_m < 0.0:
            fail("toe_radius_m", self.toe_radius_m, "toe_radius_m >= 0")
        if self.course != "point" and self.length_m <= 0.0:
            fail("length_m", self.length_m, "length_m > 0")
        if not isinstance(self.arc_facets, int) or not 1 <= self.arc_facets <= 16:
            fail("arc_facets", self.arc_facets, "an integer in [1, 16]")
        if not 0.5 <= self.max_turn_deg <= 15.0:
            fail("max_turn_deg", self.max_turn_deg, "0.5 <= max_turn_deg <= 15")
        if self.field_margin_m < 1.0:
            fail("field_margin_m", self.field_margin_m, "field_margin_m >= 1")
        rounding_drop = (self.hinge_radius_m + self.toe_radius_m) * (1 - math.cos(math.radians(self.slope_deg)))
        if rounding_drop >= self.depth_m:
            fail("hinge_radius_m + toe_radius_m", self.hinge_radius_m + self.toe_radius_m,
                 f"small enough that the rounded edges drop less than depth_m={self.depth_m} "
                 f"(they drop {rounding_drop:.3f} m)")
        for index, wall in enumerate(self.walls):
            _validate_wall(index, wall)
        _validate_wall_slopes(self)
        if self.course == "sine":
            if self.sine_amplitude_m < 0.0:
                fail("sine_amplitude_m", self.sine_amplitude_m, "sine_amplitude_m >= 0")
            if self.sine_wavelength_m <= 0.0:
                fail("sine_wavelength_m", self.sine_wavelength_m, "sine_wavelength_m > 0")
            curvature = self.sine_amplitude_m * (2 * math.pi / self.sine_wavelength_m) ** 2
            limit = min_bend_radius_m(self)
            if curvature > 0 and 1.0 / curvature < limit:
                fail("sine_amplitude_m", self.sine_amplitude_m,
                     f"a bend radius 1 / (A (2 pi / L_w)^2) ({1 / curvature:.2f} m) of at least min_bend_radius_m "
                     f"({limit:.2f} m); lower the amplitude or lengthen the wavelength")
        if self.course == "arc":
            if self.arc_radius_m <= 0.0:
                fail("arc_radius_m", self.arc_radius_m, "arc_radius_m > 0")
            if self.length_m / self.arc_radius_m > math.pi:
                fail("length_m", self.length_m, f"an arc's sweep length_m / arc_radius_m <= pi (180 deg): "
                     f"length_m <= {math.pi * self.arc_radius_m:.2f} m for arc_radius_m={self.arc_radius_m}")
            limit = min_bend_radius_m(self)
            if self.arc_radius_m < limit:
                fail("arc_radius_m", self.arc_radius_m,
                     f"a bend radius ({self.arc_radius_m:.2f} m) of at least min_bend_radius_m ({limit:.2f} m)")


# How far the box pieces reach past the hinge onto flat ground (m), with `box_pieces`'
# default 1 m ground cells: the cell's diagonal plus 5 cm.
FLAT_REACH_M = math.sqrt(2.0) + 0.05


def min_bend_radius_m(params: TerrainParams) -> float:
    """The tightest bend radius (m) of a "sine" or "arc" course for which the collision
    geometry (`DitchTerrain.box_pieces`) still matches the analytic `DitchTerrain.height`
    (measured: `python -m ditch_drake.docs_tools.bend_limit`, docs/concepts/terrain_family.md).

    On a bend's inner side the pieces of one segment reach straight out from it; past the
    bend's centre of curvature they lie over ground nearer to another part of the course,
    and stand too high: the wall folds over itself.
    - "sine": the bend is tight only near its apex, and the fold grows slowly past it; the
      limit is where the straight wall ends and the hinge's rounding begins,
      hinge distance - hinge_radius_m * sin(slope_deg).
    - "arc": the whole course bends at one radius; up to a half circle, the pieces
      revolved round one end (and the segments next to it) reach across to ground nearest
      the other end once the radius drops below hinge distance + FLAT_REACH_M / 2.
    """
    hinge = params.bottom_width_m / 2 + _profile_width(params)
    if params.course == "arc":
        return hinge + FLAT_REACH_M / 2
    return hinge - params.hinge_radius_m * math.sin(math.radians(params.slope_deg))


def _unchecked_terrain(params: TerrainParams) -> "DitchTerrain":
    """A `DitchTerrain` built without `TerrainParams.validate` (for measuring the limits)."""
    terrain = DitchTerrain.__new__(DitchTerrain)
    terrain._build(params)
    return terrain


def _validate_wall(index: int, wall: Wall) -> None:
    points = np.asarray(wall.points, dtype=float) if wall.points else np.zeros((0, 2))
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 2 or not np.all(np.isfinite(points)):
        raise TerrainError(f"terrain parameter walls[{index}].points={wall.points!r} is out of range: expected "
                           "at least two finite [x, y] points")
    if np.any(np.linalg.norm(np.diff(points, axis=0), axis=1) < 1e-6):
        raise TerrainError(f"terrain parameter walls[{index}].points={wall.points!r} repeats a point: expected "
                           "segments of positive length")
    for name, allowed, ok in (("height_m", "0 < height_m <= 10", 0.0 < wall.height_m <= 10.0),
                              ("thickness_m", "0 < thickness_m <= 2", 0.0 < wall.thickness_m <= 2.0)):
        if not ok:
            raise TerrainError(f"terrain parameter walls[{index}].{name}={getattr(wall, name)!r} is out of range: "
                               f"expected {allowed}")


def _validate_wall_slopes(params: TerrainParams) -> None:
    """Raises TerrainError naming the first section out of range (`TerrainParams.wall_slopes`)."""

    def fail(name, value, allowed):
        raise TerrainError(f"terrain parameter wall_slopes.{name}={value!r} is out of range: expected {allowed}")

    for side in WALL_SIDES:
        sections = getattr(params.wall_slopes, side)
        if sections and params.course != "line":
            raise TerrainError(f"terrain parameter wall_slopes.{side} is set for course={params.course!r}: expected "
                               "course 'line' (walls whose slope varies are built on a straight ditch only; "
                               "docs/concepts/terrain_family.md)")
        reached = 0.0
        for index, section in enumerate(sections):
            key = f"{side}[{index}]"
            for name in ("from_m", "to_m", "slope_deg"):
                value = getattr(section, name)
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                    fail(f"{key}.{name}", value, "a finite number")
            if not 0.0 < section.slope_deg < 90.0:
                fail(f"{key}.slope_deg", section.slope_deg, "0 < slope_deg < 90")
            drop = (params.hinge_radius_m + params.toe_radius_m) * (1 - math.cos(math.radians(section.slope_deg)))
            if drop >= params.depth_m:
                fail(f"{key}.slope_deg", section.slope_deg,
                     f"a slope at which the rounded edges (hinge_radius_m + toe_radius_m) drop less than "
                     f"depth_m={params.depth_m} (they drop {drop:.3f} m)")
            if section.from_m < reached - SECTION_TOLERANCE_M:
                where = "the course's start" if index == 0 else f"{side}[{index - 1}]'s end"
                fail(f"{key}.from_m", section.from_m, f"{reached:g}, {where}: it overlaps the section before it "
                     f"by {reached - section.from_m:g} m")
            if section.from_m > reached + SECTION_TOLERANCE_M:
                where = "the course's start" if index == 0 else f"{side}[{index - 1}]'s end"
                fail(f"{key}.from_m", section.from_m, f"{reached:g}, {where}: it leaves a gap of "
                     f"{section.from_m - reached:g} m without a slope")
            if section.to_m <= section.from_m:
                fail(f"{key}.to_m", section.to_m, f"to_m > from_m ({section.from_m:g})")
            reached = section.to_m
        if sections and abs(reached - params.length_m) > SECTION_TOLERANCE_M:
            past = "reaches past the course's end" if reached > params.length_m else "leaves a gap before its end"
            fail(f"{side}[{len(sections) - 1}].to_m", reached,
                 f"length_m={params.length_m:g}: the sections cover the wall's whole length (it {past})")


def _profile_width(params: TerrainParams, slope_deg: float | None = None) -> float:
    """Horizontal distance from the bottom's edge to the end of the hinge (m), for a wall at
    `slope_deg` (None: `params.slope_deg`)."""
    alpha = math.radians(params.slope_deg if slope_deg is None else slope_deg)
    rounding = (params.hinge_radius_m + params.toe_radius_m)
    wall_drop = params.depth_m - rounding * (1 - math.cos(alpha))
    return rounding * math.sin(alpha) + wall_drop / math.tan(alpha)


@dataclass(frozen=True)
class BoxPiece:
    """One collision/visual box: size (m), pose (rotation matrix R_WP, centre p_WP)."""

    size: np.ndarray
    R_WP: np.ndarray
    p_WP: np.ndarray
    kind: str  # "floor", "wall" (the ditch's sides), "ground" or "barrier" (a fence), for colouring


@dataclass(frozen=True)
class ConvexPiece:
    """One convex collision piece: the convex hull of `vertices_W` (N, 3), in world (m)."""

    vertices_W: np.ndarray
    kind: str

    @staticmethod
    def hull_of(boxes: list[BoxPiece]) -> "ConvexPiece":
        """The piece whose hull holds the boxes' corners."""
        corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
        vertices = np.concatenate([(box.R_WP @ (corners * box.size).T).T + box.p_WP for box in boxes])
        return ConvexPiece(vertices, boxes[0].kind)

    def top_height(self, xy: np.ndarray) -> np.ndarray:
        """Height (m) of the hull's upper surface over points xy (N, 2); -inf outside it."""
        equations = ConvexHull(self.vertices_W).equations  # n . p + offset <= 0 inside
        n_xy, n_z, offset = equations[:, :2], equations[:, 2], equations[:, 3]
        level = xy @ n_xy.T + offset  # (N, faces): n_z * z + level <= 0
        up, down, side = n_z > 1e-12, n_z < -1e-12, np.abs(n_z) <= 1e-12
        top = np.min(-level[:, up] / n_z[up], axis=1)
        bottom = np.max(-level[:, down] / n_z[down], axis=1) if down.any() else np.full(len(xy), -np.inf)
        inside = (bottom <= top + 1e-9) & np.all(level[:, side] <= 1e-9, axis=1)
        return np.where(inside, top, -np.inf)


class DitchTerrain:
    """Analytic terrain and its box-piece geometry for one `TerrainParams`."""

    def __init__(self, params: TerrainParams):
        params.validate()
        self._build(params)

    def _build(self, params: TerrainParams) -> None:
        self.params = params
        self._alpha = math.radians(params.slope_deg)
        self._half_bottom = params.bottom_width_m / 2
        self._profile_s, self._profile_h = self._make_profile()
        self._widest_s = float(self._profile_s[-1])
        self._make_wall_sections()
        self.course_xy = self._make_course()
        starts, ends = self.course_xy[:-1], self.course_xy[1:]
        self._seg_start = starts
        self._seg_vec = ends - starts
        self._seg_len2 = np.maximum(np.sum(self._seg_vec**2, axis=1), 1e-300)
        self._check_walls_off_the_floor()
        self._pieces_made: dict[tuple, list] = {}

    # ----- walls ----------------------------------------------------------------------
    @property
    def walled(self) -> bool:
        """Whether the field is fenced (`TerrainParams.walls`)."""
        return bool(self.params.walls)

    def wall_segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every wall segment: start points (K, 2), end points (K, 2), half thicknesses (K,) (m)."""
        starts, ends, half = [], [], []
        for wall in self.params.walls:
            points = np.asarray(wall.points, dtype=float)
            starts.append(points[:-1])
            ends.append(points[1:])
            half.append(np.full(len(points) - 1, wall.thickness_m / 2))
        if not starts:
            return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
        return np.concatenate(starts), np.concatenate(ends), np.concatenate(half)

    def distance_to_walls(self, xy: np.ndarray) -> np.ndarray:
        """Planar distance (m) from points xy (..., 2) to the nearest wall's surface (inf: no walls)."""
        xy = np.asarray(xy, dtype=float)
        starts, ends, half = self.wall_segments()
        if len(starts) == 0:
            return np.full(xy.shape[:-1], np.inf)
        return _distance_to_segments(xy.reshape(-1, 2), starts, ends, half).reshape(xy.shape[:-1])

    def _check_walls_off_the_floor(self) -> None:
        """Raises TerrainError when a wall passes over the ditch's floor (it would cross the ditch)."""
        for index, wall in enumerate(self.params.walls):
            points = np.asarray(wall.points, dtype=float)
            samples = np.concatenate([np.linspace(a, b, max(2, math.ceil(np.linalg.norm(b - a) / 0.05) + 1))
                                      for a, b in itertools.pairwise(points)])
            distance = self.nearest_on_course(samples)[0]
            inside = distance < self.toe_distance_m + wall.thickness_m / 2
            if inside.any():
                x, y = samples[np.argmax(inside)]
                raise TerrainError(f"walls[{index}] crosses the ditch: its point ({x:.2f}, {y:.2f}) lies over the "
                                   f"ditch's floor (within {self.toe_distance_m:.2f} m of the course); a wall may "
                                   "reach into the sloping sides, not across the floor")

    def wall_pieces(self) -> list[BoxPiece]:
        """The walls' collision/visual boxes, one per segment (kind "barrier"), from the ditch's
        floor level up to each wall's height; each is a thickness longer than its segment so
        that the corners of a polyline close."""
        pieces = []
        bottom = -self.params.depth_m - 0.5
        for wall in self.params.walls:
            for a, b in itertools.pairwise(np.asarray(wall.points, dtype=float)):
                heading = math.atan2(*(b - a)[::-1])
                c, s = math.cos(heading), math.sin(heading)
                R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
                size = np.array([float(np.linalg.norm(b - a)) + wall.thickness_m, wall.thickness_m,
                                 wall.height_m - bottom])
                center = np.array([*(a + b) / 2, (wall.height_m + bottom) / 2])
                pieces.append(BoxPiece(size, R, center, "barrier"))
        return pieces

    # ----- cross-section profile -------------------------------------------------
    def _make_profile(self, slope_deg: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Breakpoints (s, h) of the profile of a wall at `slope_deg` (None: `slope_deg` of the
        params): s is distance outward from the bottom's edge."""
        p = self.params
        alpha = self._alpha if slope_deg is None else math.radians(slope_deg)
        width = _profile_width(p, slope_deg)
        thetas = np.linspace(0.0, alpha, p.arc_facets + 1)
        toe = np.stack([p.toe_radius_m * np.sin(thetas), -p.depth_m + p.toe_radius_m * (1 - np.cos(thetas))], axis=1)
        phis = thetas[::-1]
        hinge = np.stack([width - p.hinge_radius_m * np.sin(phis), -p.hinge_radius_m * (1 - np.cos(phis))], axis=1)
        points = np.concatenate([toe, hinge])
        # Zero-radius edges repeat a breakpoint; drop the repeats.
        keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9])
        points = points[keep]
        return points[:, 0], points[:, 1]

    @property
    def max_curvature_per_m(self) -> float:
        """The course's largest curvature (1/m): 0 for a line or a point, A (2 pi / L_w)^2
        for a sine, 1 / arc_radius_m for an arc."""
        p = self.params
        if p.course == "sine":
            return p.sine_amplitude_m * (2 * math.pi / p.sine_wavelength_m) ** 2
        if p.course == "arc":
            return 1.0 / p.arc_radius_m
        return 0.0

    @property
    def half_width_m(self) -> float:
        """Distance from the course to the outer end of the hinge (m); where the walls' slope
        varies, of the gentlest section's (the widest)."""
        return self._half_bottom + self._widest_s

    @property
    def hinge_distance_m(self) -> float:
        """Distance from the course where the ground starts to drop: the hinge line (m); where
        the walls' slope varies, the gentlest section's (steeper sections start to drop nearer
        the course, `hinge_distance_at`)."""
        return self.half_width_m

    @property
    def toe_distance_m(self) -> float:
        """Distance from the course where the bottom ends: the toe line (m)."""
        return self._half_bottom

    def profile_height(self, d: np.ndarray) -> np.ndarray:
        """Height (m) at planar distance d (m) from the course, of a wall at `slope_deg` (the
        walls all along, unless `wall_slopes` varies them: then `height`)."""
        s = np.asarray(d, dtype=float) - self._half_bottom
        return np.interp(s, self._profile_s, self._profile_h, left=-self.params.depth_m, right=0.0)

    def profile_slope(self, d: np.ndarray) -> np.ndarray:
        """dh/dd of the faceted profile (rises away from the course), of a wall at `slope_deg`
        (as `profile_height`)."""
        s = np.asarray(d, dtype=float) - self._half_bottom
        return _facet_slope(self._profile_s, self._profile_h, s)

    # ----- walls whose slope varies ----------------------------------------------
    @property
    def sectioned(self) -> bool:
        """Whether a wall's slope varies along the course (`TerrainParams.wall_slopes`)."""
        return self._sections is not None

    def _make_wall_sections(self) -> None:
        """Per wall side, its sections' starts, ends and profile numbers, and the profiles (one per
        distinct slope); `_sections` None when neither wall has sections."""
        p = self.params
        if not (p.wall_slopes.right or p.wall_slopes.left):
            self._sections = None
            return
        self._section_slopes: list[float] = []
        self._section_profiles: list[tuple[np.ndarray, np.ndarray]] = []
        self._sections = {}
        for side in WALL_SIDES:
            sections = self.slope_sections(side)
            numbers = []
            for section in sections:
                if section.slope_deg not in self._section_slopes:
                    self._section_slopes.append(section.slope_deg)
                    self._section_profiles.append(self._make_profile(section.slope_deg))
                numbers.append(self._section_slopes.index(section.slope_deg))
            self._sections[side] = (np.array([s.from_m for s in sections], dtype=float),
                                    np.array([s.to_m for s in sections], dtype=float), np.array(numbers))
        self._widest_s = max(float(s[-1]) for s, _ in self._section_profiles)

    def slope_sections(self, side: str) -> list[SlopeSection]:
        """The sections of the wall on `side` ("right" or "left", `WALL_SIDES`) from the course's
        start to its end: `wall_slopes`' own, or one at `slope_deg` all along."""
        if side not in WALL_SIDES:
            raise TerrainError(f"wall side {side!r} is unknown: expected one of {WALL_SIDES}")
        sections = getattr(self.params.wall_slopes, side)
        if sections:
            return [SlopeSection(s.from_m, s.to_m, s.slope_deg) for s in sections]
        length = self.params.length_m if self.params.course != "point" else 0.0
        return [SlopeSection(0.0, length, self.params.slope_deg)]

    def _sectioned_profile(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points xy (N, 2) of a terrain whose walls have sections: the height (m), dh/dd and
        the section's slope (deg) of the wall section each point faces.

        A point faces the section that holds its nearest course point, on its side of the
        course; on a boundary between two sections (and on the course's line past an end,
        between the walls' end sections) the higher of the two profiles: the steeper section's,
        as the geometry's union of pieces has it.
        """
        a, vec = self._seg_start[0], self._seg_vec[0]
        length = math.sqrt(float(self._seg_len2[0]))
        rel = xy - a
        along = np.clip(rel @ vec / length, 0.0, length)
        left_of = vec[0] * rel[:, 1] - vec[1] * rel[:, 0]  # > 0: left of the course
        d, _ = self.nearest_on_course(xy)
        s = d - self._half_bottom
        heights = np.stack([np.interp(s, sb, hb, left=-self.params.depth_m, right=0.0)
                            for sb, hb in self._section_profiles])
        slopes = np.stack([_facet_slope(sb, hb, s) for sb, hb in self._section_profiles])
        candidates, usable = [], []
        for side, on_side in (("right", left_of <= 0.0), ("left", left_of >= 0.0)):
            starts, ends, numbers = self._sections[side]
            last = len(starts) - 1
            # The section that begins at or before the point, and the one that ends at or after
            # it: the same one except on a boundary.
            candidates.append(numbers[np.clip(np.searchsorted(starts, along, side="right") - 1, 0, last)])
            candidates.append(numbers[np.clip(np.searchsorted(ends, along, side="left"), 0, last)])
            usable += [on_side, on_side]
        candidates, usable = np.stack(candidates), np.stack(usable)
        columns = np.arange(len(xy))
        chosen = candidates[np.argmax(np.where(usable, heights[candidates, columns], -np.inf), axis=0), columns]
        return heights[chosen, columns], slopes[chosen, columns], np.asarray(self._section_slopes)[chosen]

    def section_slope_deg(self, xy: np.ndarray) -> np.ndarray:
        """The slope (deg) of the wall section that points xy (..., 2) face (`slope_deg` where
        no wall has sections): the section holding the nearest course point, on the point's
        side of the course."""
        xy = np.asarray(xy, dtype=float)
        if not self.sectioned:
            return np.full(xy.shape[:-1], float(self.params.slope_deg))
        return self._sectioned_profile(xy.reshape(-1, 2))[2].reshape(xy.shape[:-1])

    def hinge_distance_at(self, xy: np.ndarray) -> np.ndarray:
        """Distance (m) from the course to the hinge line of the wall section that points xy
        (..., 2) face: `hinge_distance_m` where no wall has sections."""
        slopes = self.section_slope_deg(xy)
        widths = {slope: _profile_width(self.params, slope) for slope in np.unique(slopes).tolist()}
        return self._half_bottom + np.vectorize(widths.__getitem__, otypes=[float])(slopes)

    # ----- course ----------------------------------------------------------------
    def _make_course(self) -> np.ndarray:
        p = self.params
        if p.course == "point":
            return np.zeros((2, 2))  # a zero-length segment: distance to the origin
        if p.course == "arc":
            sweep = p.length_m / p.arc_radius_m
            count = max(2, math.ceil(sweep / math.radians(p.max_turn_deg) - 1e-9))
            phi = np.linspace(-sweep / 2, sweep / 2, count + 1)
            return np.stack([p.arc_radius_m * np.sin(phi), p.arc_radius_m * (1 - np.cos(phi))], axis=1)
        if p.course == "line" or p.sine_amplitude_m == 0.0:
            return np.array([[-p.length_m / 2, 0.0], [p.length_m / 2, 0.0]])
        k = 2 * math.pi / p.sine_wavelength_m
        max_curvature = p.sine_amplitude_m * k**2
        arc_length = p.length_m * math.sqrt(1 + (p.sine_amplitude_m * k) ** 2)
        count = max(2, math.ceil(arc_length * max_curvature / math.radians(p.max_turn_deg)))
        x = np.linspace(-p.length_m / 2, p.length_m / 2, count + 1)
        return np.stack([x, p.sine_amplitude_m * np.sin(k * x)], axis=1)

    def _nearest_segments(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points (n, 2): the nearest course segment's index, the parameter t in [0, 1]
        of the nearest point on it, and the squared distance to that point."""
        rel = flat[:, None, :] - self._seg_start[None, :, :]
        t = np.clip(np.einsum("nmk,mk->nm", rel, self._seg_vec) / self._seg_len2, 0.0, 1.0)
        closest = self._seg_start[None] + t[..., None] * self._seg_vec[None]
        dist2 = np.sum((flat[:, None, :] - closest) ** 2, axis=2)
        best = np.argmin(dist2, axis=1)
        rows = np.arange(len(flat))
        return best, t[rows, best], dist2[rows, best]

    def nearest_on_course(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns (d, c): distance (m) and nearest course point for points (..., 2)."""
        xy = np.asarray(xy, dtype=float)
        best, t, dist2 = self._nearest_segments(xy.reshape(-1, 2))
        c = self._seg_start[best] + t[:, None] * self._seg_vec[best]
        return np.sqrt(dist2).reshape(xy.shape[:-1]), c.reshape(xy.shape)

    def beyond_edge_m(self, xy: np.ndarray) -> np.ndarray:
        """Planar distance (m) of points xy (..., 2) outside the ditch's hinge line (negative inside it)."""
        return self.nearest_on_course(xy)[0] - self.hinge_distance_m

    def course_left_ahead(self, xy, direction) -> float:
        """Course length (m) from the course point nearest to `xy` to the course's end that
        `direction` (a planar vector) points to along the course; inf for a crater (a
        point course has no ends)."""
        if self.params.course == "point":
            return math.inf
        (segment,), (t,), _ = self._nearest_segments(np.asarray(xy, dtype=float).reshape(1, 2))
        lengths = np.sqrt(self._seg_len2)
        behind = float(lengths[:segment].sum() + t * lengths[segment])
        forward = float(np.asarray(direction, dtype=float) @ self._seg_vec[segment]) >= 0.0
        return float(lengths.sum()) - behind if forward else behind

    def distance_and_away(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (m) to the course and the unit direction away from it, for xy (..., 2).

        The direction is the one in which the terrain rises on the walls; the edge
        runs perpendicular to it. On the course itself it is undefined and +y is
        returned.
        """
        xy = np.asarray(xy, dtype=float)
        d, c = self.nearest_on_course(xy)
        safe = d[..., None] > 1e-9
        away = np.where(safe, (xy - c) / np.maximum(d[..., None], 1e-9), np.array([0.0, 1.0]))
        return d, away

    def away_from_course(self, xy: np.ndarray) -> np.ndarray:
        """Unit horizontal direction away from the course at xy (..., 2); see `distance_and_away`."""
        return self.distance_and_away(xy)[1]

    # ----- analytic queries ------------------------------------------------------
    def height(self, xy: np.ndarray) -> np.ndarray:
        """Terrain height z (m) at points xy (..., 2)."""
        if self.sectioned:
            xy = np.asarray(xy, dtype=float)
            return self._sectioned_profile(xy.reshape(-1, 2))[0].reshape(xy.shape[:-1])
        d, _ = self.nearest_on_course(xy)
        return self.profile_height(d)

    def normal(self, xy: np.ndarray) -> np.ndarray:
        """Unit upward surface normal (..., 3) at points xy (..., 2)."""
        d, n = self.distance_and_away(xy)
        if self.sectioned:
            slope = self._sectioned_profile(np.asarray(xy, dtype=float).reshape(-1, 2))[1].reshape(d.shape)[..., None]
        else:
            slope = self.profile_slope(d)[..., None]
        normal = np.concatenate([-slope * n, np.ones(slope.shape)], axis=-1)
        return normal / np.linalg.norm(normal, axis=-1, keepdims=True)

    def edge_lines(self, which: str = "hinge", spacing_m: float = 0.25) -> list[np.ndarray]:
        """Polylines (K, 2) at the hinge (top edge) or toe (bottom edge) distance."""
        if which not in ("hinge", "toe"):
            raise TerrainError(f"edge line {which!r} is unknown: expected 'hinge' or 'toe'")
        radius = self.hinge_distance_m if which == "hinge" else self.toe_distance_m
        samples = self._sample_level_set(radius, spacing_m)
        return [samples]

    def _sample_level_set(self, radius: float, spacing_m: float) -> np.ndarray:
        """Points at distance `radius` from the course, in order around it."""
        points = []
        course = self.course_xy
        if self.params.course == "point":
            count = max(8, math.ceil(2 * math.pi * radius / spacing_m))
            phi = np.linspace(0, 2 * math.pi, count, endpoint=False)
            return radius * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        dense = []
        for a, b in itertools.pairwise(course):
            count = max(1, math.ceil(np.linalg.norm(b - a) / spacing_m))
            dense.append(a + np.linspace(0, 1, count, endpoint=False)[:, None] * (b - a))
        dense.append(course[-1:])
        dense = np.concatenate(dense)
        tangents = np.gradient(dense, axis=0)
        tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
        left = np.stack([-tangents[:, 1], tangents[:, 0]], axis=1)
        cap_count = max(4, math.ceil(math.pi * radius / spacing_m))
        end_heading = math.atan2(tangents[-1, 1], tangents[-1, 0])
        start_heading = math.atan2(tangents[0, 1], tangents[0, 0])
        end_cap = dense[-1] + radius * np.stack(
            [np.cos(end_heading - np.pi / 2 + np.linspace(0, np.pi, cap_count)),
             np.sin(end_heading - np.pi / 2 + np.linspace(0, np.pi, cap_count))], axis=1)
        start_cap = dense[0] + radius * np.stack(
            [np.cos(start_heading + np.pi / 2 + np.linspace(0, np.pi, cap_count)),
             np.sin(start_heading + np.pi / 2 + np.linspace(0, np.pi, cap_count))], axis=1)
        points = np.concatenate([dense - radius * left, end_cap, (dense + radius * left)[::-1], start_cap])
        return points

    # ----- geometry --------------------------------------------------------------
    def bounds_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners of the flat field around the ditch (m)."""
        reach = self.half_width_m + self.params.field_margin_m
        return self.course_xy.min(axis=0) - reach, self.course_xy.max(axis=0) + reach

    def box_pieces(self, ground_cell_m: float = 1.0, thickness_m: float = 0.5,
                   mitre_bends: bool = False, convex_sections: bool = False) -> list[BoxPiece | ConvexPiece]:
        """Boxes whose upper faces form the terrain: the visual geometry, and with the defaults
        the reference that `collision_pieces` approximates with fewer boxes.

        Args:
            ground_cell_m: cell size of the flat-ground boxes.
            thickness_m: thickness of the profile's slabs.
            mitre_bends: close the outer side of each bend of the course by lengthening the
                two neighbouring segments' slabs until they meet (mitred) instead of by
                revolved wedge pieces: the surface there is lower by at most
                slope * d * (1 - cos(turn / 2)) (about 1 cm on the sine ditch's 6 degree
                bends), and the bends need no pieces of their own.
            convex_sections: each section's slabs (one segment's side, one revolved step) from
                the wall up, where the profile only bends downwards so that the solid under
                it is convex, as one `ConvexPiece` (their hull); the toe's slabs stay boxes.

        The pieces are made once per set of arguments (a scene asks twice: its illustration
        and its lidar's perception geometry).
        """
        key = (ground_cell_m, thickness_m, mitre_bends, convex_sections)
        if key not in self._pieces_made:
            make = self._make_sectioned_pieces if self.sectioned else self._make_pieces
            self._pieces_made[key] = make(*key)
        return list(self._pieces_made[key])

    def _make_pieces(self, ground_cell_m: float, thickness_m: float, mitre_bends: bool,
                     convex_sections: bool) -> list[BoxPiece | ConvexPiece]:
        pieces = self._floor_piece()
        # The profile pieces reach past the hinge far enough to close the staircase
        # gap left by the flat-ground cells (`_profile_facets` does the same).
        flat_reach = ground_cell_m * math.sqrt(2.0) + 0.05
        d_breaks = np.concatenate([self._half_bottom + self._profile_s, [self.half_width_m + flat_reach]])
        h_breaks = np.concatenate([self._profile_h, [0.0]])
        facets = [(d_breaks[i], d_breaks[i + 1], h_breaks[i], h_breaks[i + 1]) for i in range(len(d_breaks) - 1)]
        course = self.course_xy
        segments = [(a, b) for a, b in itertools.pairwise(course) if np.linalg.norm(b - a) > 1e-9]
        headings = [math.atan2(*(b - a)[::-1]) for a, b in segments]
        # turns[i]: heading change where segment i starts (0 at the course's ends).
        turns = [0.0] + [_wrap(headings[i] - headings[i - 1]) for i in range(1, len(segments))] + [0.0]
        # The steepest facet is the wall: the profile bends only upwards before it (the toe)
        # and only downwards from it on (the hinge, the flat edge).
        first_convex = int(np.argmax([(h1 - h0) / (d1 - d0) for d0, d1, h0, h1 in facets]))
        if convex_sections:
            # The wall's plane continued down to the floor's height lies under the toe (which
            # bends upwards into it): in the convex piece it buries the piece's lower end, whose
            # edge would otherwise stand at the top of the toe.
            d0, d1, h0, h1 = facets[first_convex]
            slope = (h1 - h0) / (d1 - d0)
            facets = facets + [(d0 - (h0 + self.params.depth_m) / slope, d1, -self.params.depth_m, h1)]
        sections: list[list[BoxPiece]] = []
        for i, ((a, b), heading) in enumerate(zip(segments, headings)):
            for side in (+1.0, -1.0):
                normal_angle = heading + side * math.pi / 2
                if mitre_bends:
                    sections.append([_swept_piece(a, b, normal_angle, facet, thickness_m, _mitre(turns[i], side, facet[1]),
                                                  _mitre(turns[i + 1], side, facet[1])) for facet in facets])
                else:
                    sections.append([_swept_piece(a, b, normal_angle, facet, thickness_m) for facet in facets])
        step = math.radians(self.params.max_turn_deg)
        if not segments:  # a crater: revolve the profile all the way round
            sections += _revolved_sections(course[0], 0.0, 2 * math.pi, step, facets, thickness_m)
        else:
            # Ends: half turns; bends: the wedge on the outer side (unless mitred).
            sections += _revolved_sections(segments[0][0], headings[0] + math.pi / 2, math.pi, step, facets,
                                           thickness_m)
            sections += _revolved_sections(segments[-1][1], headings[-1] - math.pi / 2, math.pi, step, facets,
                                           thickness_m)
            for i in range(1, len(segments) if not mitre_bends else 0):
                turn = _wrap(headings[i] - headings[i - 1])
                if abs(turn) < 1e-9:
                    continue
                # A left turn opens a wedge on the right side, a right turn on the left.
                if turn > 0:
                    start = headings[i - 1] - math.pi / 2
                else:
                    start = headings[i - 1] + math.pi / 2 + turn
                sections += _revolved_sections(segments[i][0], start, abs(turn), step, facets, thickness_m)
        for section in sections:
            if convex_sections:
                pieces += section[:first_convex] + [ConvexPiece.hull_of(section[first_convex:])]
            else:
                pieces += section
        pieces += self._ground_pieces(ground_cell_m)
        return pieces

    def _make_sectioned_pieces(self, ground_cell_m: float, thickness_m: float, mitre_bends: bool,
                               convex_sections: bool) -> list[BoxPiece | ConvexPiece]:
        """`_make_pieces` for a straight ditch whose walls have sections: the course cut where any
        section ends, each piece of it swept with its own section's profile on each side, each
        quarter of an end revolved with the end section of its wall, and a step's filler
        (`_step_fillers`) wherever a wall changes slope. A straight course has no bends, so
        `mitre_bends` changes nothing."""
        pieces = self._floor_piece()
        outer = self.half_width_m + ground_cell_m * math.sqrt(2.0) + 0.05
        facets = [_profile_facets(self._half_bottom + s, h, outer) for s, h in self._section_profiles]
        extended = [_with_wall_below_toe(f, self.params.depth_m) if convex_sections else f for f in facets]
        a, b = self.course_xy
        length = float(np.linalg.norm(b - a))
        tangent = (b - a) / length
        heading = math.atan2(tangent[1], tangent[0])
        left = np.array([-tangent[1], tangent[0]])
        cuts = np.unique(np.concatenate([np.concatenate(self._sections[side][:2]) for side in WALL_SIDES]))
        sections: list[tuple[int, list[BoxPiece]]] = []
        for u0, u1 in itertools.pairwise(cuts):
            if u1 - u0 < 1e-9:
                continue
            for side_sign, side in ((+1.0, "left"), (-1.0, "right")):
                number = self._section_number(side, (u0 + u1) / 2)
                sections.append((number, [_swept_piece(a + u0 * tangent, a + u1 * tangent,
                                                       heading + side_sign * math.pi / 2, facet, thickness_m)
                                          for facet in extended[number]]))
        step = math.radians(self.params.max_turn_deg)
        # Each end's half turn in two quarters, each with its own wall's end section: at the start
        # from the left wall round to the right, at the end from the right round to the left. Where
        # the two differ, the steeper quarter's pieces keep off the course's line past the end.
        quarters = ((a, heading + math.pi / 2, "left", 0.0, False), (a, heading + math.pi, "right", 0.0, True),
                    (b, heading - math.pi / 2, "right", length, False), (b, heading, "left", length, True))
        for center, start, side, along_m, line_at_start in quarters:
            number = self._section_number(side, along_m)
            other = self._section_number("left" if side == "right" else "right", along_m)
            if self._section_slopes[number] > self._section_slopes[other]:
                revolved = _revolved_beside_step(center, start, math.pi / 2, step, extended[number], thickness_m,
                                                 line_at_start)
            else:
                revolved = _revolved_sections(center, start, math.pi / 2, step, extended[number], thickness_m)
            sections += [(number, section) for section in revolved]
        for number, section in sections:
            if convex_sections:
                wall = _steepest_facet(facets[number])
                pieces += section[:wall] + [ConvexPiece.hull_of(section[wall:])]
            else:
                pieces += section
        pieces += self._step_fillers(facets, tangent, left)
        pieces += self._ground_pieces(ground_cell_m)
        return pieces

    def _section_number(self, side: str, along_m: float) -> int:
        """The profile number of the section of `side`'s wall that holds `along_m` (m)."""
        starts, _, numbers = self._sections[side]
        return int(numbers[min(max(int(np.searchsorted(starts, along_m, side="right")) - 1, 0), len(starts) - 1)])

    def _step_fillers(self, facets: list[list[tuple]], tangent: np.ndarray, left: np.ndarray) -> list[BoxPiece]:
        """The pieces that close each step where a wall changes slope.

        The steeper section's profile stands above the gentler one's everywhere; its slabs end
        at the boundary, and below them the step would be open down to the gentler surface. At
        each step, under each facet of the steeper profile that the gentler one lies below,
        a slab `STEP_FILLER_LENGTH_M` long reaches down `depth_m` + 0.5 m inside the steeper
        section. Its face toward the gentler section is the step's face; it leans back by
        `STEP_FACE_LEAN_RAD`, so that it faces a little upward: the renderer draws the
        terrain's upward faces only (`ditch_drake.world.box_mesh`)."""
        a, b = self.course_xy
        length = float(np.linalg.norm(b - a))
        heading = math.atan2(tangent[1], tangent[0])
        steps = []  # (origin, angle of the profile's outward direction, into the steeper side, steep, gentle)
        for side_sign, side in ((+1.0, "left"), (-1.0, "right")):
            starts, _, numbers = self._sections[side]
            for boundary, before, after in zip(starts[1:], numbers[:-1], numbers[1:]):
                if before != after:
                    steeper = after if self._section_slopes[after] > self._section_slopes[before] else before
                    steps.append((a + boundary * tangent, heading + side_sign * math.pi / 2,
                                  tangent if steeper == after else -tangent, steeper, before + after - steeper))
        # On the course's line past each end, between the two walls' end sections.
        for center, outward, along_m in ((a, -tangent, 0.0), (b, tangent, length)):
            right, left_number = self._section_number("right", along_m), self._section_number("left", along_m)
            if right != left_number:
                left_steeper = self._section_slopes[left_number] > self._section_slopes[right]
                steps.append((center, math.atan2(outward[1], outward[0]), left if left_steeper else -left,
                              left_number if left_steeper else right, right if left_steeper else left_number))
        fillers = []
        for origin, angle, into, steep, gentle in steps:
            gentle_hinge = self._half_bottom + float(self._section_profiles[gentle][0][-1])
            fillers += [_step_filler(origin, angle, into, facet, self.params.depth_m + 0.5)
                        for facet in facets[steep] if facet[0] < gentle_hinge]
        return fillers

    @property
    def winding(self) -> bool:
        """Whether the course bends (a sine or an arc)."""
        return len(self.course_xy) > 2

    def collision_pieces(self) -> list[BoxPiece | ConvexPiece]:
        """The collision geometry. A straight ditch's or a crater's: `box_pieces`. A winding
        ditch's: `box_pieces` with mitred bends (no wedge pieces at the bends) and convex
        sections, the packaged sine's 1975 boxes cut to 785 pieces.

        Drake's collision filter keeps an entry for every pair of proximity geometries, twice
        in the geometry model and twice again in each Context, so a scene's memory and build
        time grow with the square of the number of pieces (`ditch_drake.perf.bench_scene`,
        docs/results/benchmark.md). A convex section has the surface of its slabs' tops, and a sphere
        touching it gets one contact point instead of one per slab it reaches. Straight ditches
        and craters, a few hundred pieces, keep the slabs. The visual geometry stays
        `box_pieces`, so the lidar sees the same terrain either way.
        """
        if not self.winding:
            return self.box_pieces()
        return self.box_pieces(mitre_bends=True, convex_sections=True)

    def _floor_piece(self) -> list[BoxPiece]:
        low, high = self.course_xy.min(axis=0) - self.half_width_m, self.course_xy.max(axis=0) + self.half_width_m
        size = np.array([*(high - low), 1.0])
        center = np.array([*(low + high) / 2, -self.params.depth_m - 0.5])
        return [BoxPiece(size, np.eye(3), center, "floor")]

    def _ground_pieces(self, cell: float) -> list[BoxPiece]:
        """Flat ground everywhere the ditch does not reach, merged into few boxes."""
        low, high = self.bounds_xy()
        nx, ny = (np.ceil((high - low) / cell)).astype(int)
        xs = low[0] + (np.arange(nx) + 0.5) * cell
        ys = low[1] + (np.arange(ny) + 0.5) * cell
        grid = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)
        d, _ = self.nearest_on_course(grid)
        flat = d >= self.half_width_m + cell / math.sqrt(2.0)
        # Runs of flat cells along each row, then identical runs stacked over rows.
        runs: dict[tuple[int, int], list[int]] = {}
        for row in range(ny):
            padded = np.concatenate([[False], flat[row], [False]])
            changes = np.flatnonzero(np.diff(padded.astype(int)))
            for begin, end in zip(changes[::2], changes[1::2]):
                runs.setdefault((begin, end), []).append(row)
        pieces = []
        for (begin, end), rows in runs.items():
            rows = np.array(rows)
            breaks = np.flatnonzero(np.diff(rows) > 1)
            for block in np.split(rows, breaks + 1):
                x0, x1 = low[0] + begin * cell, low[0] + end * cell
                y0, y1 = low[1] + block[0] * cell, low[1] + (block[-1] + 1) * cell
                pieces.append(BoxPiece(np.array([x1 - x0, y1 - y0, 1.0]), np.eye(3),
                                       np.array([(x0 + x1) / 2, (y0 + y1) / 2, -0.5]), "ground"))
        return pieces

    def pieces_height(self, xy: np.ndarray, pieces: list[BoxPiece | ConvexPiece] | None = None) -> np.ndarray:
        """Height of the union of the pieces' upper surfaces at points xy (N, 2).

        Used by tests to check the collision geometry against `height`.
        """
        pieces = self.box_pieces() if pieces is None else pieces
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        top = np.full(len(xy), -np.inf)
        for piece in pieces:
            if isinstance(piece, ConvexPiece):
                top = np.maximum(top, piece.top_height(xy))
                continue
            normal = piece.R_WP[:, 2]
            if normal[2] < 1e-6:
                continue
            top_center = piece.p_WP + normal * piece.size[2] / 2
            # Height of the top face's plane at xy, then keep points inside its footprint.
            z = top_center[2] - (normal[0] * (xy[:, 0] - top_center[0]) + normal[1] * (xy[:, 1] - top_center[1])) / normal[2]
            p = np.column_stack([xy, z]) - top_center
            local = p @ piece.R_WP
            inside = (np.abs(local[:, 0]) <= piece.size[0] / 2 + 1e-9) & (np.abs(local[:, 1]) <= piece.size[1] / 2 + 1e-9)
            top = np.where(inside, np.maximum(top, z), top)
        return top


# A step's filler (`DitchTerrain._step_fillers`): how far it reaches into the steeper section (m),
# and how far its face leans back from the vertical (rad): enough for an upward face on walls up to
# 87 deg (`box_mesh.UP_FACE_MIN_NORMAL_Z`), little enough that the step's foot stands out less than
# 2 cm per metre of its height.
STEP_FILLER_LENGTH_M = 0.1
STEP_FACE_LEAN_RAD = 0.02


def _profile_facets(d_breaks: np.ndarray, h_breaks: np.ndarray, outer_m: float) -> list[tuple]:
    """The profile's facets (d0, d1, h0, h1) from its breakpoints at distances `d_breaks` from the
    course, on to flat ground at `outer_m` (the flat-ground cells' reach)."""
    d = np.concatenate([d_breaks, [outer_m]])
    h = np.concatenate([h_breaks, [0.0]])
    return [(d[i], d[i + 1], h[i], h[i + 1]) for i in range(len(d) - 1)]


def _steepest_facet(facets: list[tuple]) -> int:
    """The wall's facet: the profile bends only upwards before it (the toe), only downwards after."""
    return int(np.argmax([(h1 - h0) / (d1 - d0) for d0, d1, h0, h1 in facets]))


def _with_wall_below_toe(facets: list[tuple], depth_m: float) -> list[tuple]:
    """The facets and the wall's plane continued down to the floor's height under the toe (for
    convex sections, `DitchTerrain.box_pieces`)."""
    d0, d1, h0, h1 = facets[_steepest_facet(facets)]
    slope = (h1 - h0) / (d1 - d0)
    return facets + [(d0 - (h0 + depth_m) / slope, d1, -depth_m, h1)]


def _facet_slope(s_breaks: np.ndarray, h_breaks: np.ndarray, s: np.ndarray) -> np.ndarray:
    """dh/ds of the faceted profile with breakpoints (s_breaks, h_breaks) at s (0 off its ends)."""
    slopes = np.diff(h_breaks) / np.diff(s_breaks)
    index = np.searchsorted(s_breaks, s, side="right") - 1
    inside = (index >= 0) & (index < len(slopes))
    return np.where(inside, slopes[np.clip(index, 0, len(slopes) - 1)], 0.0)


def _step_filler(origin: np.ndarray, normal_angle: float, into: np.ndarray, facet, thickness_m: float) -> BoxPiece:
    """A slab under `facet` of a profile about `origin` (as `_facet_piece`), `STEP_FILLER_LENGTH_M`
    long toward `into` (a horizontal unit vector) from 5 mm before the boundary through
    `origin`, `thickness_m` thick, turned about its uphill edge on the boundary so that its face
    toward -`into` leans back by `STEP_FACE_LEAN_RAD`."""
    d0, d1, h0, h1 = facet
    n = np.array([math.cos(normal_angle), math.sin(normal_angle)])
    uphill = np.array([n[0] * (d1 - d0), n[1] * (d1 - d0), h1 - h0])
    width = float(np.linalg.norm(uphill))
    up = np.array([-n[0] * (h1 - h0), -n[1] * (h1 - h0), d1 - d0])
    up /= np.linalg.norm(up)
    x = np.array([into[0], into[1], 0.0])
    lean = STEP_FACE_LEAN_RAD
    x_lean, z_lean = math.cos(lean) * x - math.sin(lean) * up, math.sin(lean) * x + math.cos(lean) * up
    R = np.column_stack([x_lean, np.cross(z_lean, x_lean), z_lean])
    edge = np.array([*(origin + n * (d0 + d1) / 2), (h0 + h1) / 2]) - 0.005 * x
    center = edge + x_lean * STEP_FILLER_LENGTH_M / 2 - z_lean * thickness_m / 2
    return BoxPiece(np.array([STEP_FILLER_LENGTH_M, width, thickness_m]), R, center, "wall")


def _distance_to_segments(xy: np.ndarray, starts: np.ndarray, ends: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Distance (N,) from points (N, 2) to the nearest of the segments' thick bodies (0 inside)."""
    vec = ends - starts
    length2 = np.maximum(np.sum(vec**2, axis=1), 1e-300)
    best = np.full(len(xy), np.inf)
    for start, v, l2, h in zip(starts, vec, length2, half, strict=True):  # Few segments, many points.
        t = np.clip((xy - start) @ v / l2, 0.0, 1.0)
        gap = np.linalg.norm(xy - (start + t[:, None] * v), axis=1) - h
        np.minimum(best, gap, out=best)
    return np.maximum(best, 0.0)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _facet_piece(origin: np.ndarray, normal_angle: float, facet, along_m: float, thickness_m: float) -> BoxPiece:
    """A box whose top face spans distances [d0, d1] from `origin` along a
    horizontal direction at `normal_angle`, rising from h0 to h1, `along_m` long."""
    d0, d1, h0, h1 = facet
    n = np.array([math.cos(normal_angle), math.sin(normal_angle)])
    uphill = np.array([n[0] * (d1 - d0), n[1] * (d1 - d0), h1 - h0])
    width = float(np.linalg.norm(uphill))
    uphill /= width
    up = np.array([-n[0] * (h1 - h0), -n[1] * (h1 - h0), d1 - d0])
    up /= np.linalg.norm(up)
    # uphill x up, written out: np.cross costs more than the rest of a piece (the packaged
    # sine builds thousands), and gives the same numbers.
    across = np.array([uphill[1] * up[2] - uphill[2] * up[1], uphill[2] * up[0] - uphill[0] * up[2],
                       uphill[0] * up[1] - uphill[1] * up[0]])
    R = np.column_stack([across, uphill, up])
    top_center = np.array([*(origin + n * (d0 + d1) / 2), (h0 + h1) / 2])
    return BoxPiece(np.array([along_m, width, thickness_m]), R, top_center - up * thickness_m / 2, "wall")


def _swept_piece(a, b, normal_angle, facet, thickness_m, extend_start_m: float = 0.005,
                 extend_end_m: float = 0.005) -> BoxPiece:
    """A slab along the segment a -> b, reaching past a and b by the given lengths (m)."""
    length = float(np.linalg.norm(b - a))
    if extend_start_m == extend_end_m == 0.005:  # the unmitred pieces, in their own arithmetic
        return _facet_piece((a + b) / 2, normal_angle, facet, length + 0.01, thickness_m)
    origin = (a + b) / 2 + (b - a) / length * (extend_end_m - extend_start_m) / 2
    return _facet_piece(origin, normal_angle, facet, length + extend_start_m + extend_end_m, thickness_m)


def _mitre(turn: float, side: float, outer_distance_m: float) -> float:
    """How far a slab on `side` (+1 left, -1 right) of a segment reaches past a course vertex
    where the course turns by `turn` (rad, > 0 left): on the bend's outer side (a left turn's
    right) until it meets the other segment's slab at `outer_distance_m`, else 5 mm."""
    if turn * side < 0:
        return outer_distance_m * math.tan(abs(turn) / 2) + 0.005
    return 0.005


def _revolved_sections(center, start_angle, sweep, step, facets, thickness_m) -> list[list[BoxPiece]]:
    """The profile's slabs revolved around `center` in steps of at most `step` (rad), a list per step."""
    count = max(1, math.ceil(sweep / step - 1e-9))
    width = sweep / count
    sections = []
    for k in range(count):
        angle = start_angle + (k + 0.5) * width
        # Each slab spans the chord at its outer radius, so that neighbours leave no gap.
        sections.append([_facet_piece(np.asarray(center), angle, facet, 2 * facet[1] * math.tan(width / 2) + 0.01,
                                      thickness_m) for facet in facets])
    return sections


def _revolved_beside_step(center, start_angle, sweep, step, facets, thickness_m,
                          step_at_start: bool) -> list[list[BoxPiece]]:
    """`_revolved_sections`, with no piece reaching past the ray at the sweep's start
    (`step_at_start`) or end, where the wall steps down to a gentler profile.

    A revolved slab spans its step's chord at its outer distance, so it reaches past its step's
    rays nearer the centre: harmless between steps of one profile, but past a step it would
    stand above the gentler side. The step next to the ray gets slabs whose side toward it
    meets the ray at their inner distance and keeps inside beyond; the sliver left between
    them and the ray, at most (d1 - d0) tan(width / 2) wide, is covered by a slab along the
    ray (its own section, so that a convex section's hull stays in one step)."""
    count = max(1, math.ceil(sweep / step - 1e-9))
    width = sweep / count
    sections = []
    for k in range(count):
        angle = start_angle + (k + 0.5) * width
        if k != (0 if step_at_start else count - 1):
            sections.append([_facet_piece(np.asarray(center), angle, facet, 2 * facet[1] * math.tan(width / 2) + 0.01,
                                          thickness_m) for facet in facets])
            continue
        line_angle = start_angle if step_at_start else start_angle + sweep
        ray = np.array([math.cos(angle), math.sin(angle)])
        line = np.array([math.cos(line_angle), math.sin(line_angle)])
        toward_line = line - (line @ ray) * ray
        toward_line /= np.linalg.norm(toward_line)
        into_step = ray - (ray @ line) * line
        into_step /= np.linalg.norm(into_step)
        slabs, strips = [], []
        for facet in facets:
            d0, d1 = facet[0], facet[1]
            far, near = d1 * math.tan(width / 2) + 0.005, max(d0, 0.0) * math.tan(width / 2)
            slabs.append(_facet_piece(np.asarray(center) + toward_line * (near - far) / 2, angle, facet, near + far,
                                      thickness_m))
            strip = (d1 - max(d0, 0.0)) * math.tan(width / 2) + 0.005
            strips.append(_facet_piece(np.asarray(center) + into_step * strip / 2, line_angle, facet, strip,
                                       thickness_m))
        sections += [slabs, strips]
    return sections
