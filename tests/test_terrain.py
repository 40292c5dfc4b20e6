"""The terrain family: analytic queries, collision geometry, bad parameters."""

import math

import numpy as np
import pytest

from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain, TerrainError, TerrainParams

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
