"""Walls whose slope varies along the course: the analytic queries, the geometry built from the
sections (steps included), and the sections' bad values."""

import itertools

import numpy as np
import pytest

from ditch_drake.world.box_mesh import UP_FACE_MIN_NORMAL_Z
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import (
    STEP_FILLER_LENGTH_M,
    DitchTerrain,
    SlopeSection,
    TerrainError,
    TerrainParams,
    WallSlopes,
)

SEARCH = ["wide_search", "wide_search_offset"]


def _sections(*stretches):
    return [SlopeSection(a, b, slope) for a, b, slope in stretches]


def _steps_at_the_ends() -> DitchTerrain:
    """A 40 m ditch whose walls differ at both ends (a step round each rounded end) and change
    slope at different places, one of them three times."""
    return DitchTerrain(TerrainParams(
        course="line", length_m=40.0, bottom_width_m=4.0, slope_deg=55.0,
        wall_slopes=WallSlopes(right=_sections((0, 8, 70), (8, 20, 45), (20, 40, 65)),
                               left=_sections((0, 15, 50), (15, 22, 72), (22, 31, 55), (31, 40, 48)))))


def _terrains():
    return [DitchTerrain(get_environment(name).terrain) for name in SEARCH] + [_steps_at_the_ends()]


def _boundaries_x(terrain: DitchTerrain) -> np.ndarray:
    """x of every place along the course where a wall changes slope."""
    start = terrain.course_xy[0, 0]
    return np.unique([start + s.from_m for side in ("right", "left") for s in terrain.slope_sections(side)[1:]])


def _error(terrain, points, pieces=None):
    return terrain.pieces_height(points, pieces if pieces is not None else terrain.box_pieces()) - terrain.height(points)


@pytest.mark.parametrize("index", range(3))
def test_the_pieces_reproduce_the_sectioned_height_away_from_the_steps(index):
    terrain = _terrains()[index]
    rng = np.random.default_rng(0)
    half_length, reach = terrain.params.length_m / 2, terrain.half_width_m + 2.0
    points = np.column_stack([rng.uniform(-half_length - reach, half_length + reach, 8000),
                              rng.uniform(-reach, reach, 8000)])
    # The step is vertical at the boundary (and on the course's line past an end, between the
    # walls' end sections); the slabs reach 5 mm past their section's end.
    off_steps = np.min(np.abs(points[:, :1] - _boundaries_x(terrain)[None]), axis=1) > 0.01
    off_steps &= (np.abs(points[:, 1]) > 0.01) | (np.abs(points[:, 0]) < half_length)
    assert np.max(np.abs(_error(terrain, points[off_steps]))) < 0.03
    # The collision set of a straight ditch is the visual one, fillers included.
    assert len(terrain.collision_pieces()) == len(terrain.box_pieces())


def test_each_side_of_a_step_has_its_own_section_s_height_and_slope():
    for terrain in _terrains():
        start = terrain.course_xy[0, 0]
        cases = []  # (x, side's sign of y, the section's slope)
        for side, sign in (("right", -1.0), ("left", 1.0)):
            sections = terrain.slope_sections(side)
            for before, after in itertools.pairwise(sections):
                x = start + after.from_m
                cases += [(x + offset, sign, section.slope_deg)
                          for section, offset in ((before, -0.01), (after, 0.01), (before, -0.5), (after, 0.5))]
            cases += [(start + (s.from_m + s.to_m) / 2, sign, s.slope_deg) for s in sections]
        _check_wall_slopes(terrain, np.array(cases))


def _check_wall_slopes(terrain, cases: np.ndarray):
    """Halfway up the wall at each case's x on its side: the analytic normal and the pieces' surface
    both slope at the case's slope, and the section's queries name it."""
    x, sign, slope_deg = cases.T
    toe = terrain.toe_distance_m
    hinge = terrain.hinge_distance_at(np.column_stack([x, sign * (toe + 0.1)]))
    d = (toe + hinge) / 2
    points = np.column_stack([x, sign * d])
    assert np.array_equal(terrain.section_slope_deg(points), slope_deg)
    np.testing.assert_allclose(np.degrees(np.arccos(terrain.normal(points)[:, 2])), slope_deg, atol=0.01)
    below, above = np.column_stack([x, sign * (d - 0.05)]), np.column_stack([x, sign * (d + 0.05)])
    geometry = terrain.pieces_height(np.concatenate([below, above])).reshape(2, -1)
    np.testing.assert_allclose(np.degrees(np.arctan((geometry[1] - geometry[0]) / 0.1)), slope_deg, atol=0.5)
    np.testing.assert_allclose(geometry, terrain.height(np.stack([below, above])), atol=0.01)


def test_on_a_boundary_the_steeper_section_holds():
    terrain = DitchTerrain(get_environment("wide_search").terrain)
    # The right wall's window (50 deg) begins 5 m along the 60 m course, at x = -25 m.
    on, gentle, steep = np.array([-25.0, -4.5]), np.array([-24.99, -4.5]), np.array([-25.01, -4.5])
    assert float(terrain.height(steep)) > float(terrain.height(gentle)) + 1.0
    assert float(terrain.height(on)) == float(terrain.height(steep))
    assert float(terrain.section_slope_deg(on)) == 70.0 and float(terrain.section_slope_deg(gentle)) == 50.0
    # The hinge line is the gentlest section's; a steep section starts to drop nearer the course.
    assert terrain.hinge_distance_m == pytest.approx(float(terrain.hinge_distance_at(gentle)))
    assert float(terrain.hinge_distance_at(steep)) < terrain.hinge_distance_m - 1.5


def test_the_steps_are_closed_and_their_faces_face_upward():
    """Under the steeper section's surface at a step, down to the gentler one's, every point lies
    inside a piece (no wheel or lidar ray gets under the steeper slabs), and each filler's face
    toward the gentler side tilts up enough for the renderer's upward faces (`box_mesh`)."""
    terrain = _steps_at_the_ends()
    pieces = terrain.box_pieces()
    fillers = [p for p in pieces if p.kind == "wall" and p.size[0] == STEP_FILLER_LENGTH_M]
    assert len(fillers) >= 5 * (2 + 3 + 2)  # right: two changes; left: three; both ends
    assert all(-filler.R_WP[2, 0] > UP_FACE_MIN_NORMAL_Z for filler in fillers)
    start, toe = terrain.course_xy[0, 0], terrain.toe_distance_m
    checked = 0
    for x_step in _boundaries_x(terrain):
        for sign in (-1.0, 1.0):
            d = np.linspace(toe, terrain.half_width_m, 40)
            before = terrain.height(np.column_stack([np.full(40, x_step - 0.01), sign * d]))
            after = terrain.height(np.column_stack([np.full(40, x_step + 0.01), sign * d]))
            if np.allclose(before, after):
                continue  # this wall does not change slope here
            into = 1.0 if after.sum() > before.sum() else -1.0
            high, low = np.maximum(before, after), np.minimum(before, after)
            for fraction in np.linspace(0.05, 0.95, 7):
                z = low + fraction * (high - low)
                gap = high - low > 0.05
                points = np.column_stack([np.full(gap.sum(), x_step + 0.02 * into), sign * d[gap], z[gap]])
                assert _inside_any(pieces, points).all(), (x_step, sign)
                checked += len(points)
    assert checked > 500 and start < 0


def _inside_any(pieces, points: np.ndarray) -> np.ndarray:
    """Which points (N, 3) lie inside one of the box pieces."""
    inside = np.zeros(len(points), dtype=bool)
    for piece in pieces:
        local = (points - piece.p_WP) @ piece.R_WP
        inside |= np.all(np.abs(local) <= piece.size / 2 + 1e-9, axis=1)
    return inside


def test_one_section_all_along_is_the_single_slope():
    plain = TerrainParams(course="line", length_m=30.0, bottom_width_m=6.0)
    whole = _sections((0, 30, 55.0))
    sectioned = DitchTerrain(TerrainParams(course="line", length_m=30.0, bottom_width_m=6.0,
                                           wall_slopes=WallSlopes(right=whole, left=whole)))
    terrain = DitchTerrain(plain)
    assert sectioned.sectioned and not terrain.sectioned
    rng = np.random.default_rng(5)
    points = rng.uniform([-25, -10], [25, 10], (5000, 2))
    assert np.array_equal(sectioned.height(points), terrain.height(points))
    assert np.array_equal(sectioned.normal(points), terrain.normal(points))
    assert sectioned.half_width_m == terrain.half_width_m
    assert np.max(np.abs(sectioned.pieces_height(points) - terrain.pieces_height(points))) < 0.02


def test_the_packaged_ditches_have_no_sections():
    for name in ["crater", "wide", "narrow", "sine", "wide_walled"]:
        terrain = DitchTerrain(get_environment(name).terrain)
        assert not terrain.sectioned
        assert [(s.from_m, s.to_m, s.slope_deg) for s in terrain.slope_sections("left")] == [
            (0.0, terrain.params.length_m if terrain.params.course != "point" else 0.0, terrain.params.slope_deg)]


@pytest.mark.parametrize("right, name, expected", [
    (((0, 10, 70), (10, 30, 95)), "right[1].slope_deg=95", "0 < slope_deg < 90"),
    (((0, 10, 70), (10, 30, 0)), "right[1].slope_deg=0", "0 < slope_deg < 90"),
    (((0, 10, 70), (10, 30, -5)), "right[1].slope_deg=-5", "0 < slope_deg < 90"),
    (((0, 12, 70), (10, 30, 50)), "right[1].from_m=10", "overlaps the section before it by 2 m"),
    (((0, 10, 70), (11, 30, 50)), "right[1].from_m=11", "leaves a gap of 1 m"),
    (((2, 10, 70), (10, 30, 50)), "right[0].from_m=2", "leaves a gap of 2 m"),
    (((0, 10, 70), (10, 25, 50)), "right[1].to_m=25", "length_m=30: the sections cover the wall's whole length"),
    (((0, 10, 70), (10, 35, 50)), "right[1].to_m=35", "reaches past the course's end"),
    (((0, 10, 70), (10, 10, 50), (10, 30, 50)), "right[1].to_m=10", "to_m > from_m"),
    (((0, 10, 70), (10, 30, float("nan"))), "right[1].slope_deg=nan", "a finite number"),
])
def test_bad_sections_are_named(right, name, expected):
    params = TerrainParams(course="line", length_m=30.0, wall_slopes=WallSlopes(right=_sections(*right)))
    with pytest.raises(TerrainError) as error:
        DitchTerrain(params)
    assert f"wall_slopes.{name}" in str(error.value) and expected in str(error.value)


def test_sections_need_a_straight_course():
    params = TerrainParams(course="sine", sine_amplitude_m=2.0, wall_slopes=WallSlopes(left=_sections((0, 30, 50))))
    with pytest.raises(TerrainError, match=r"wall_slopes.left is set for course='sine': expected course 'line'"):
        DitchTerrain(params)


def test_the_lidar_sees_a_step_s_face():
    """On the floor of wide_search's window, looking along the right wall at the step where it turns
    steep again (x = -5 m): the cloud holds points on the step's face, between the two walls'
    surfaces (without its fillers the rays pass under the steep slabs and none are there)."""
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.systems.framework import DiagramBuilder

    from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
    from ditch_drake.diagrams.lidar_rig import AddLidar

    X_WB = RigidTransform(RotationMatrix.MakeZRotation(-0.3), [-7.0, -1.5, -4.0 + 0.165])
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment="wide_search"))
    lidar = AddLidar(builder, scene)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant = scene.plant
    plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(context), plant.GetBodyByName("chassis", scene.husky),
                          X_WB)
    converter_context = lidar.converter.GetMyMutableContextFromRoot(context)
    lidar.converter.ExecuteForcedEvents(converter_context)
    p_W = (X_WB @ lidar.X_BL).multiply(lidar.converter.GetOutputPort("point_cloud").Eval(converter_context).xyzs())
    p_W = p_W[:, np.all(np.isfinite(p_W), axis=0)]
    near = p_W[:, (np.abs(p_W[0] + 5.0) < 0.1) & (p_W[1] < -3.2)]
    steep = scene.terrain.height(np.column_stack([np.full(near.shape[1], -4.99), near[1]]))
    gentle = scene.terrain.height(np.column_stack([np.full(near.shape[1], -5.01), near[1]]))
    assert np.sum((near[2] < steep - 0.1) & (near[2] > gentle + 0.1)) > 30
