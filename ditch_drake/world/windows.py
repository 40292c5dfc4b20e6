"""The crossable windows of a ditch whose walls change slope along the course.

A straight ditch's walls may each change slope along the course (`TerrainParams.wall_slopes`).
Where a wall is steeper than the robot can stand on, it is closed; a window is a run of
adjacent sections no steeper than a limit (by default the robot's smallest static tip-over
angle, `smallest_tip_angle_deg`), merged into one interval along the course. The load-time
check (`ingress.check_windows`), the scripted expert's route (`systems/window_route.py`) and
anything that draws or generates such ditches read the windows from here.

Positions along the course run from the course's start (as `SlopeSection.from_m`); a wall's
side is "right" or "left" of the course facing along it (`terrain.WALL_SIDES`).
"""

import math
from dataclasses import dataclass

import numpy as np

from ditch_drake.spec import robot
from ditch_drake.world.terrain import WALL_SIDES, DitchTerrain, _profile_width


def smallest_tip_angle_deg() -> float:
    """The robot's smallest static tip-over angle (deg): about its axles, 59.6 deg today
    (`robot.tip_angle_fore_aft_rad`; 61.6 deg about a wheel line)."""
    return math.degrees(min(robot.tip_angle_fore_aft_rad(), robot.tip_angle_sideways_rad()))


@dataclass(frozen=True)
class CourseFrame:
    """A straight course's frame in the ground plane: its start, unit direction along it and
    the unit normal to its left (m)."""

    origin: np.ndarray
    tangent: np.ndarray
    left: np.ndarray

    def side_sign(self, side: str) -> float:
        """+1 for the "left" wall, -1 for the "right" one."""
        return 1.0 if side == "left" else -1.0

    def along_and_offset(self, xy) -> tuple[np.ndarray, np.ndarray]:
        """Position along the course (m from its start) and signed offset from its line (m, > 0
        on the left) of points xy (..., 2)."""
        rel = np.asarray(xy, dtype=float) - self.origin
        return rel @ self.tangent, rel @ self.left

    def point(self, along_m, offset_m) -> np.ndarray:
        """The point `along_m` along the course and `offset_m` to its left (negative: right)."""
        return self.origin + np.multiply.outer(along_m, self.tangent) + np.multiply.outer(offset_m, self.left)

    def side_of(self, xy) -> str:
        """The wall side ("right" or "left") of planar point `xy`."""
        return "left" if float(self.along_and_offset(xy)[1]) > 0.0 else "right"


def course_frame(terrain: DitchTerrain) -> CourseFrame:
    """The frame of `terrain`'s course from its first to its last point (a "line" course's
    exactly; walls whose slope varies are built on "line" courses only)."""
    start, end = terrain.course_xy[0], terrain.course_xy[-1]
    tangent = (end - start) / max(float(np.linalg.norm(end - start)), 1e-12)
    return CourseFrame(start.copy(), tangent, np.array([-tangent[1], tangent[0]]))


@dataclass(frozen=True)
class Window:
    """A run of adjacent wall sections no steeper than a limit, on one wall.

    Attributes:
        side: the wall, "right" or "left" of the course.
        first_section: index of its first section in `terrain.slope_sections(side)`.
        last_section: index of its last one.
        from_m: where it begins along the course (m from the course's start).
        to_m: where it ends (m).
        slope_deg: its steepest section's slope.
        hinge_distance_m: the farthest from the course that its wall begins to drop (its
            gentlest section's hinge line, m): the robot leaves the flat there at the latest.
        from_xy: the world point on that hinge line across from `from_m`.
        to_xy: the one across from `to_m`.
    """

    side: str
    first_section: int
    last_section: int
    from_m: float
    to_m: float
    slope_deg: float
    hinge_distance_m: float
    from_xy: tuple[float, float]
    to_xy: tuple[float, float]

    @property
    def width_m(self) -> float:
        """Its length along the course (m)."""
        return self.to_m - self.from_m

    @property
    def middle_m(self) -> float:
        """Its middle along the course (m)."""
        return (self.from_m + self.to_m) / 2

    def holds(self, along_m: float, margin_m: float = 0.0) -> bool:
        """Whether `along_m` lies in it, at least `margin_m` from both its ends."""
        return self.from_m + margin_m <= along_m <= self.to_m - margin_m


def _limit(max_slope_deg: float | None) -> float:
    return smallest_tip_angle_deg() if max_slope_deg is None else float(max_slope_deg)


def crossable_windows(terrain: DitchTerrain, side: str, max_slope_deg: float | None = None) -> list[Window]:
    """The windows of the wall on `side`: runs of adjacent sections (`terrain.slope_sections`)
    no steeper than `max_slope_deg` (None: `smallest_tip_angle_deg`), in order along the course."""
    limit = _limit(max_slope_deg)
    sections = terrain.slope_sections(side)
    frame = course_frame(terrain)
    sign = frame.side_sign(side)
    toe = terrain.toe_distance_m
    windows, first = [], None
    for index, section in enumerate([*sections, None]):
        crossable = section is not None and section.slope_deg <= limit
        if crossable and first is None:
            first = index
        if crossable or first is None:
            continue
        run = sections[first:index]
        hinge = toe + max(_profile_width(terrain.params, s.slope_deg) for s in run)
        begin, end = run[0].from_m, run[-1].to_m
        windows.append(Window(side, first, index - 1, begin, end, max(s.slope_deg for s in run), hinge,
                              tuple(frame.point(begin, sign * hinge).tolist()),
                              tuple(frame.point(end, sign * hinge).tolist())))
        first = None
    return windows


def windows_by_side(terrain: DitchTerrain, max_slope_deg: float | None = None) -> dict[str, list[Window]]:
    """`crossable_windows` of both walls, keyed by side."""
    return {side: crossable_windows(terrain, side, max_slope_deg) for side in WALL_SIDES}


def has_steep_sections(terrain: DitchTerrain, max_slope_deg: float | None = None) -> bool:
    """Whether a wall of `terrain` has a section (`TerrainParams.wall_slopes`) steeper than
    `max_slope_deg` (None: `smallest_tip_angle_deg`): then it can be crossed only in windows."""
    if not terrain.sectioned:
        return False
    limit = _limit(max_slope_deg)
    return any(section.slope_deg > limit for side in WALL_SIDES for section in terrain.slope_sections(side))
