"""The terrain family: analytic queries, collision geometry, bad parameters."""

import math

import numpy as np
import pytest

from ditch_drake.world.bypass import _near_course
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import (
    BoxPiece,
    ConvexPiece,
    DitchTerrain,
    TerrainError,
    TerrainParams,
    min_bend_radius_m,
)

ENVIRONMENTS = ["crater", "wide", "narrow", "sine"]


@pytest.mark.parametrize("name", ENVIRONMENTS)
def test_box_pieces_reproduce_the_analytic_height(name):
    terrain = DitchTerrain(get_environment(name).terrain)
    rng = np.random.default_rng(0)
    reach = terrain.half_width_m + 2.0
    near = terrain.course_xy[rng.integers(0, len(terrain.course_xy), 6000)] + rng.uniform(-reach, reach, (6000, 2))
    error = terrain.pieces_height(near) - terrain.height(near)
    assert np.max(np.abs(error)) < 0.03


@pytest.mark.parametrize("name", ENVIRONMENTS)
def test_profile_depth_slope_and_flat_ground(name):
    terrain = DitchTerrain(get_environment(name).terrain)
    params = terrain.params
    assert terrain.profile_height(0.0) == pytest.approx(-params.depth_m)
    assert terrain.profile_height(terrain.half_width_m + 1.0) == 0.0
    # Halfway down the wall the slope is the wall angle.
    wall_d = terrain.toe_distance_m + (terrain.hinge_distance_m - terrain.toe_distance_m) / 2
    assert math.degrees(math.atan(terrain.profile_slope(wall_d))) == pytest.approx(params.slope_deg, abs=0.5)


def test_normal_points_up_and_tilts_on_the_wall():
    terrain = DitchTerrain(get_environment("wide").terrain)
    wall_d = (terrain.toe_distance_m + terrain.hinge_distance_m) / 2
    normal = terrain.normal(np.array([[0.0, wall_d], [0.0, -wall_d], [0.0, 20.0]]))
    assert normal[:, 2] == pytest.approx([math.cos(math.radians(55))] * 2 + [1.0], abs=0.01)
    # On the +y wall the ground rises toward +y, so the normal leans toward -y.
    assert normal[0, 1] < 0 < normal[1, 1]


def test_sine_course_follows_the_sine():
    params = get_environment("sine").terrain
    terrain = DitchTerrain(params)
    x = 7.5
    y = params.sine_amplitude_m * math.sin(2 * math.pi * x / params.sine_wavelength_m)
    assert float(terrain.height(np.array([x, y]))) == pytest.approx(-params.depth_m)
    assert float(terrain.height(np.array([x, y + terrain.half_width_m + 0.5]))) == 0.0


def test_edge_lines_lie_at_the_hinge():
    terrain = DitchTerrain(get_environment("crater").terrain)
    (hinge,) = terrain.edge_lines("hinge")
    assert np.allclose(np.linalg.norm(hinge, axis=1), terrain.hinge_distance_m)
    # Beyond the edge: 0 on the hinge line, the crater's centre as deep inside as the line is far.
    points = np.array([hinge[0], [0.0, 0.0], [terrain.hinge_distance_m + 2.0, 0.0]])
    assert np.allclose(terrain.beyond_edge_m(points), [0.0, -terrain.hinge_distance_m, 2.0], atol=1e-9)


@pytest.mark.parametrize("field, value, expected", [
    ("slope_deg", 90.0, "0 < slope_deg < 90"),
    ("slope_deg", -5.0, "0 < slope_deg < 90"),
    ("depth_m", 0.0, "depth_m > 0"),
    ("course", "spiral", "one of"),
    ("bottom_width_m", -1.0, "bottom_width_m >= 0"),
    ("hinge_radius_m", 10.0, "drop less than depth_m"),
    ("arc_facets", 0, "an integer in [1, 16]"),
    ("length_m", float("nan"), "a finite number"),
])
def test_out_of_range_parameters_are_named(field, value, expected):
    params = TerrainParams(**{field: value})
    with pytest.raises(TerrainError) as error:
        DitchTerrain(params)
    assert field.split()[0] in str(error.value) and expected in str(error.value)


def test_sine_too_tight_for_the_ditch_is_refused():
    with pytest.raises(TerrainError, match="bend radius"):
        DitchTerrain(TerrainParams(course="sine", sine_amplitude_m=6.0, sine_wavelength_m=12.0))


@pytest.mark.parametrize("name", ENVIRONMENTS)
def test_collision_pieces_are_fewer_and_match_the_visual_ones_away_from_the_ends(name):
    """Issue 22: the collision set (mitred bends) has fewer boxes where the course bends and
    stays within the visual pieces' accuracy everywhere."""
    terrain = DitchTerrain(get_environment(name).terrain)
    collision = terrain.collision_pieces()
    visual = terrain.box_pieces()
    assert len(collision) < len(visual) if terrain.params.course == "sine" else len(collision) == len(visual)
    rng = np.random.default_rng(1)
    reach = terrain.half_width_m + 2.0
    near = terrain.course_xy[rng.integers(0, len(terrain.course_xy), 6000)] + rng.uniform(-reach, reach, (6000, 2))
    error = terrain.pieces_height(near, collision) - terrain.height(near)
    assert np.max(np.abs(error)) < 0.03
    if terrain.params.course == "line":  # no bends: the crossing's pieces are the visual ones
        visual = terrain.box_pieces()
        swept = [p for p in visual if p.kind == "wall"][:len([p for p in collision if p.kind == "wall"])]
        assert all(np.array_equal(a.p_WP, b.p_WP) and np.array_equal(a.size, b.size)
                   for a, b in zip(swept[:20], [p for p in collision if p.kind == "wall"][:20]))


def test_a_winding_ditch_collides_with_convex_sections_and_the_others_with_the_visual_boxes():
    sine = DitchTerrain(get_environment("sine").terrain)
    collision = sine.collision_pieces()
    convex = [piece for piece in collision if isinstance(piece, ConvexPiece)]
    # One convex piece per section (each segment's two sides, each revolved step of the ends),
    # beside the toe's four boxes each.
    sections = 2 * (len(sine.course_xy) - 1) + 2 * 30
    assert len(convex) == sections
    assert sum(isinstance(piece, BoxPiece) and piece.kind == "wall" for piece in collision) == 4 * sections
    for name in ("wide", "crater"):
        terrain = DitchTerrain(get_environment(name).terrain)
        assert not terrain.winding
        assert all(isinstance(piece, BoxPiece) for piece in terrain.collision_pieces())


def test_the_convex_sections_lie_under_the_toe():
    """Their wall goes on down to the floor's height under the toe, so that no edge of theirs
    stands at the top of the toe (where a Husky's nose caught on it and stuck)."""
    terrain = DitchTerrain(get_environment("sine").terrain)
    convex = [piece for piece in terrain.collision_pieces() if isinstance(piece, ConvexPiece)]
    rng = np.random.default_rng(3)
    points = terrain.course_xy[rng.integers(5, len(terrain.course_xy) - 5, 20000)] + rng.uniform(-3.5, 3.5, (20000, 2))
    d, _ = terrain.nearest_on_course(points)
    grid = np.linspace(terrain.toe_distance_m, terrain.half_width_m, 4000)
    wall_foot = grid[np.argmax(terrain.profile_slope(grid))]  # where the toe ends
    toe = points[(d > wall_foot - 0.1) & (d < wall_foot - 0.01)]
    assert len(toe) > 100
    below = terrain.pieces_height(toe, convex) - terrain.height(toe)
    assert np.isfinite(below).mean() > 0.9  # their wall does reach under the toe,
    assert np.max(below[np.isfinite(below)]) < 0.005  # and stays beneath it


def test_convex_piece_top_height_is_its_hull_top():
    box = BoxPiece(np.array([2.0, 1.0, 0.5]), np.eye(3), np.array([1.0, 0.0, -0.25]), "wall")
    piece = ConvexPiece.hull_of([box])
    xy = np.array([[0.5, 0.2], [1.9, -0.4], [3.0, 0.0], [1.0, 0.6]])
    np.testing.assert_allclose(piece.top_height(xy)[:2], [0.0, 0.0], atol=1e-12)
    assert np.all(np.isneginf(piece.top_height(xy)[2:]))  # outside the footprint


@pytest.mark.parametrize("name", ["sine", "crater"])
def test_the_bypass_grid_queries_every_point_near_the_course(name):
    terrain = DitchTerrain(get_environment(name).terrain)
    rng = np.random.default_rng(4)
    low, high = terrain.bounds_xy()
    points = rng.uniform(low, high, (20000, 2))
    distance = terrain.half_width_m + 0.1
    d, _ = terrain.nearest_on_course(points)
    near = _near_course(terrain, points, distance)
    assert np.all(near[d <= distance])
    assert near.mean() < 2 * (d <= distance).mean() + 0.01  # and not many more


def _pieces_error_near(terrain, centre_xy, count=2500):
    """max |pieces_height - height| at random points within the hinge + 1 m of centre_xy, over
    the visual pieces and the collision pieces (mitred bends), the worse of the two."""
    rng = np.random.default_rng(2)
    reach = terrain.half_width_m + 1.0
    points = np.asarray(centre_xy) + rng.uniform(-reach, reach, (count, 2))
    return max(np.max(np.abs(terrain.pieces_height(points, pieces) - terrain.height(points)))
               for pieces in (terrain.box_pieces(), terrain.collision_pieces()))


def test_arc_course_builds_and_its_pieces_match_the_height():
    params = TerrainParams(course="arc", arc_radius_m=12.0, length_m=12.0 * math.pi / 2, max_turn_deg=3.0)
    terrain = DitchTerrain(params)
    assert terrain.max_curvature_per_m == pytest.approx(1 / 12.0)
    # Midpoint at the origin heading +x; every course point on the circle round (0, R).
    assert np.allclose(np.linalg.norm(terrain.course_xy - [0.0, 12.0], axis=1), 12.0)
    assert float(terrain.height(np.array([0.0, 0.0]))) == pytest.approx(-params.depth_m)
    assert float(terrain.height(np.array([0.0, 12.0]))) == 0.0
    for centre in ([0.0, 0.0], terrain.course_xy[-1], [0.0, 12.0 - terrain.hinge_distance_m]):
        assert _pieces_error_near(terrain, centre) < 0.03


def test_max_curvature_of_each_course_kind():
    assert DitchTerrain(TerrainParams(course="line")).max_curvature_per_m == 0.0
    assert DitchTerrain(TerrainParams(course="point")).max_curvature_per_m == 0.0
    sine = TerrainParams(course="sine", sine_amplitude_m=3.0, sine_wavelength_m=30.0)
    assert DitchTerrain(sine).max_curvature_per_m == pytest.approx(3.0 * (2 * math.pi / 30.0) ** 2)


def _sine_with_bend(radius_m, **kw):
    k = 2 * math.pi / 30.0
    return TerrainParams(course="sine", sine_amplitude_m=1 / (radius_m * k * k), sine_wavelength_m=30.0, **kw)


def test_sine_at_the_bend_limit_builds_and_its_pieces_match_the_height():
    limit = min_bend_radius_m(TerrainParams(course="sine"))
    assert limit < DitchTerrain(TerrainParams(course="sine")).hinge_distance_m  # tighter than the old limit
    terrain = DitchTerrain(_sine_with_bend(limit, max_turn_deg=2.0))
    assert 1 / terrain.max_curvature_per_m == pytest.approx(limit)
    apex = [7.5, terrain.params.sine_amplitude_m]  # the bend; its inner side is toward -y
    assert _pieces_error_near(terrain, apex) < 0.03


def test_bends_just_under_the_limit_are_refused():
    limit = min_bend_radius_m(TerrainParams(course="sine"))
    with pytest.raises(TerrainError, match=r"sine_amplitude_m=.*bend radius .*min_bend_radius_m"):
        DitchTerrain(_sine_with_bend(0.98 * limit))
    arc_limit = min_bend_radius_m(TerrainParams(course="arc"))
    with pytest.raises(TerrainError, match=r"arc_radius_m=.*bend radius .*min_bend_radius_m"):
        DitchTerrain(TerrainParams(course="arc", arc_radius_m=0.98 * arc_limit, length_m=10.0))
    DitchTerrain(TerrainParams(course="arc", arc_radius_m=arc_limit, length_m=10.0))


@pytest.mark.parametrize("changes, name, expected", [
    ({"arc_radius_m": 0.0}, "arc_radius_m", "arc_radius_m > 0"),
    ({"arc_radius_m": -3.0}, "arc_radius_m", "arc_radius_m > 0"),
    ({"arc_radius_m": float("inf")}, "arc_radius_m", "a finite number"),
    ({"arc_radius_m": 10.0, "length_m": 32.0}, "length_m", "length_m / arc_radius_m <= pi"),
])
def test_arc_parameters_out_of_range_are_named(changes, name, expected):
    with pytest.raises(TerrainError) as error:
        DitchTerrain(TerrainParams(course="arc", **changes))
    assert f"{name}=" in str(error.value) and expected in str(error.value)


def test_the_crossing_side_turns_toward_the_goal_and_is_held_from_the_approach_zone_on():
    from ditch_drake.world.crossing import crossing_side_step, crossing_sides

    # The packaged wide ditch runs along x; from y = -11 facing +y, +x is to the right.
    terrain = DitchTerrain(get_environment("wide").terrain)
    start = np.array([0.0, -11.0])

    def side_at(xy, goal):
        return crossing_side_step(terrain, xy, goal, 0.0, 2.5, 15.0)[0]

    assert side_at(start, [8.0, 11.0]) == 1.0  # 20 deg to the right.
    assert side_at(start, [-8.0, 11.0]) == -1.0  # 20 deg to the left.
    assert side_at(start, [-2.0, 11.0]) == 1.0  # Near square: right by convention.
    # Held from where the path enters the approach zone (hinge 6.3 m + 2.5 m), though from the
    # last point the goal lies within 15 deg of square.
    path = np.array([start, [0.0, -8.0], [-12.0, -8.0]])
    goal = np.array([-8.0, 11.0])
    assert side_at(path[2], goal) == 1.0
    assert crossing_side_step(terrain, path[0], goal, 0.0, 2.5, 15.0) == (-1.0, 0.0)
    assert crossing_side_step(terrain, path[1], goal, 0.0, 2.5, 15.0) == (-1.0, -1.0)
    assert crossing_side_step(terrain, path[2], goal, -1.0, 2.5, 15.0) == (-1.0, -1.0)
    assert crossing_sides(terrain, path, goal, 2.5, 15.0).tolist() == [-1.0, -1.0, -1.0]
    # With a narrower approach zone the path is not yet in it at y = -8.
    assert crossing_sides(terrain, path, goal, 1.0, 15.0).tolist() == [-1.0, -1.0, 1.0]
