"""Tests of the surface-normal image: the numpy functions and the NormalImageConverter system."""

import math

import numpy as np
import pytest
from pydrake.math import RollPitchYaw, RotationMatrix
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.analysis import Simulator
from scipy.spatial import cKDTree

from ditch_drake.perception import normal_image as ni
from ditch_drake.perception.normal_image import (
    IMAGE_SHAPE,
    NormalImageConfig,
    cloud_to_normal_image,
    estimate_normals_organized,
    estimate_normals_pca,
    normal_image,
    normalize_to_unit_ball,
    organized_cloud_to_normal_image,
)
from ditch_drake.perf import bench_normal_image as bench
from ditch_drake.spec import robot
from ditch_drake.systems.normal_image_converter import NormalImageConverter


def tilted_plane_grid(tilt_deg: float, rows: int = 40, cols: int = 60, axis: str = "pitch") -> np.ndarray:
    """An organized (rows, cols, 3) grid on a plane tilted by tilt_deg about y ("pitch") or x ("roll")."""
    u, v = np.meshgrid(np.linspace(0.5, 4.0, rows), np.linspace(2.0, -2.0, cols), indexing="ij")
    tilt = math.radians(tilt_deg)
    if axis == "pitch":
        grid = np.stack([u * math.cos(tilt), v, u * math.sin(tilt)], axis=-1)
    else:
        grid = np.stack([u, v * math.cos(tilt), v * math.sin(tilt)], axis=-1)
    return grid


@pytest.mark.parametrize("method", ["organized", "pca"])
@pytest.mark.parametrize("tilt_deg", [0.0, 10.0, 30.0, 55.0])
def test_tilted_plane_reads_cos_tilt(tilt_deg, method):
    grid = tilted_plane_grid(tilt_deg, axis="pitch" if tilt_deg != 30.0 else "roll")
    image = cloud_to_normal_image(grid.reshape(-1, 3), NormalImageConfig(normal_method=method), grid.shape[:2])
    assert image.shape == IMAGE_SHAPE == (128, 128)
    assert image.dtype == np.float32
    covered = image > 0.0
    assert covered.mean() > 0.15
    np.testing.assert_allclose(image[covered], math.cos(math.radians(tilt_deg)), atol=0.02)


def test_lidar_sampled_plane_reads_cos_tilt():
    # A depth image of a 20 deg slope rising ahead, as the lidar sees it (non-uniform sampling).
    tilt = math.radians(20.0)
    grid = bench.lidar_depth_cloud(30, 45, center_m=50.0)  # flat ground, the ditch far away
    x, y, z = np.moveaxis(grid, 2, 0)
    # Rotate the ground about the y axis: still a plane, now tilted.
    tilted = np.stack([x * math.cos(tilt) - z * math.sin(tilt), y, x * math.sin(tilt) + z * math.cos(tilt)], axis=-1)
    for method in ("organized", "pca"):
        image = cloud_to_normal_image(tilted.reshape(-1, 3), NormalImageConfig(normal_method=method), grid.shape[:2])
        covered = image > 0.0
        assert covered.mean() > 0.15
        np.testing.assert_allclose(image[covered], math.cos(tilt), atol=0.02)


def test_organized_normals_agree_with_pca_and_truth_on_ditch():
    # A fixed viewpoint 0.585 m above the ground, independent of the robot's lidar mount.
    grid = bench.lidar_depth_cloud(40, 60, height_m=0.585)
    points = grid.reshape(-1, 3)
    organized = estimate_normals_organized(grid).reshape(-1, 3)
    pca = estimate_normals_pca(points, k=12)
    finite = np.isfinite(points).all(axis=1)
    assert finite.sum() > 1000
    both = np.isfinite(organized[:, 2]) & np.isfinite(pca[:, 2])
    assert both.sum() >= 0.98 * finite.sum()
    np.testing.assert_allclose(np.linalg.norm(organized[both], axis=1), 1.0, atol=1e-9)
    assert (organized[both, 2] >= 0.0).all() and (pca[both, 2] >= 0.0).all()
    # Tolerance: |organized n_z - PCA n_z| median under 0.005, 95% under 0.05, all under 0.25
    # (they differ where the walls curve: PCA averages over a wider neighbourhood).
    difference = np.abs(organized[both, 2] - pca[both, 2])
    assert np.median(difference) < 0.005
    assert np.percentile(difference, 95) < 0.05
    assert difference.max() < 0.25
    # Against the analytic surface normal, across the occlusion's depth jump too.
    x, y = points[both, 0], points[both, 1]
    step = 1e-6
    dz_dx = (bench.ditch_height(x + step, y) - bench.ditch_height(x - step, y)) / (2 * step)
    dz_dy = (bench.ditch_height(x, y + step) - bench.ditch_height(x, y - step)) / (2 * step)
    truth = 1.0 / np.sqrt(1.0 + dz_dx**2 + dz_dy**2)
    error = np.abs(organized[both, 2] - truth)
    assert np.percentile(error, 99) < 0.05
    assert error.max() < 0.15


def test_organized_normals_borders_and_holes():
    grid = tilted_plane_grid(30.0, rows=6, cols=7)
    grid[2, 3] = np.nan  # a pixel without a return: its neighbours fall back to one-sided differences
    grid[4, 5, 1] = np.inf
    before = grid.copy()
    normals = estimate_normals_organized(grid)
    np.testing.assert_array_equal(grid, before)  # the input is not touched
    assert normals.shape == grid.shape
    valid = np.isfinite(grid).all(axis=2)
    assert np.isnan(normals[~valid]).all()
    # In the corner, (4, 6) has no valid neighbour along its row, (5, 5) none along its column.
    valid[4, 6] = valid[5, 5] = False
    assert np.isnan(normals[~valid]).all()
    np.testing.assert_allclose(normals[valid], np.tile([-0.5, 0.0, math.sqrt(3) / 2], (valid.sum(), 1)), atol=1e-12)
    # A single row or column has no tangent across it.
    assert np.isnan(estimate_normals_organized(grid[:1])).all()
    assert estimate_normals_organized(np.zeros((0, 5, 3))).shape == (0, 5, 3)


def test_normals_oriented_up():
    grid = tilted_plane_grid(10.0)[::-1]  # reversed rows flip the cross product
    assert (estimate_normals_organized(grid)[..., 2] > 0.9).all()
    points = grid.reshape(-1, 3)
    assert (estimate_normals_pca(points)[:, 2] > 0.9).all()


def reference_splat(x, y, values, config):
    """The image by querying a k-d tree of the grid points (slow, obvious)."""
    dx, dy = config.spacing
    rows, cols = np.meshgrid(np.arange(config.rows), np.arange(config.cols), indexing="ij")
    grid = np.stack([config.x_max - rows.ravel() * dx, config.y_max - cols.ravel() * dy], axis=1)
    image = np.zeros(config.rows * config.cols)
    softening_sq = (ni._IDW_SOFTENING * min(dx, dy)) ** 2
    floor = (config.radius**2 + softening_sq) ** (-config.idw_power / 2)
    for pixel, near in enumerate(cKDTree(np.stack([x, y], axis=1)).query_ball_point(grid, config.radius)):
        if near:
            d_sq = ((grid[pixel] - np.stack([x[near], y[near]], axis=1)) ** 2).sum(axis=1)
            w = np.maximum((d_sq + softening_sq) ** (-config.idw_power / 2) - floor, 0.0)
            if w.sum() > 0:
                image[pixel] = (w * values[near]).sum() / w.sum()
    return image.reshape(config.rows, config.cols)


@pytest.mark.parametrize(
    "config",
    [NormalImageConfig(), NormalImageConfig(rows=40, cols=30, radius=0.11, x_min=-0.5, y_max=0.7, idw_power=1.0)],
)
def test_splat_matches_kd_tree_reference(config):
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-1.1, 1.1, (2, 800))
    values = rng.uniform(0.0, 1.0, 800)
    np.testing.assert_allclose(ni._splat(x, y, values, config), reference_splat(x, y, values, config), atol=2e-5)


def test_splat_without_scratch_memory_is_the_same(monkeypatch):
    grid = bench.lidar_depth_cloud(20, 30)
    expected = cloud_to_normal_image(grid.reshape(-1, 3), organized_shape=grid.shape[:2])
    monkeypatch.setattr(ni, "_SCRATCH_MAX_ELEMENTS", 10)
    np.testing.assert_array_equal(cloud_to_normal_image(grid.reshape(-1, 3), organized_shape=grid.shape[:2]), expected)


def test_image_layout_forward_up_left_left():
    # Flat ground ahead; normals_z = 0.5 on the patch ahead (+x) and to the left (+y).
    x, y = np.meshgrid(np.linspace(0.0, 4.0, 41), np.linspace(-2.0, 2.0, 41), indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    normals_z = np.where((points[:, 0] > 2.5) & (points[:, 1] > 0.5), 0.5, 1.0)
    config = NormalImageConfig()
    image = normal_image(points, normals_z, config)
    # Normalized: centroid (2, 0), scale sqrt(8); pixel (r, c) sits at x = 1 - r dx, y = 1 - c dy.
    dx, dy = config.spacing

    def pixel(x_m, y_m):
        return round((1.0 - (x_m - 2.0) / math.sqrt(8.0)) / dx), round((1.0 - y_m / math.sqrt(8.0)) / dy)

    ahead_left, ahead_right, near_left = pixel(3.5, 1.5), pixel(3.5, -1.5), pixel(0.5, 1.5)
    assert ahead_left[0] < near_left[0] and ahead_left[1] < ahead_right[1]
    assert image[ahead_left] == pytest.approx(0.5, abs=1e-6)
    assert image[ahead_right] == pytest.approx(1.0, abs=1e-6)
    assert image[near_left] == pytest.approx(1.0, abs=1e-6)
    assert image[:64, :64][image[:64, :64] > 0].mean() < 0.8 < image[64:, :][image[64:, :] > 0].mean()


def test_normalize_to_unit_ball():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3)) * [3.0, 1.0, 0.2] + [5.0, -2.0, 1.0]
    points[7] = [np.nan, 0.0, 0.0]
    normalized = normalize_to_unit_ball(points)
    finite = np.isfinite(normalized).all(axis=1)
    assert np.isnan(normalized[7]).all() and finite.sum() == 49
    np.testing.assert_allclose(normalized[finite].mean(axis=0), 0.0, atol=1e-12)
    assert np.linalg.norm(normalized[finite], axis=1).max() == pytest.approx(1.0)
    # Uniform scaling: directions (and so normals) are unchanged.
    a, b, c = points[0], points[1], points[2]
    na, nb, nc = normalized[0], normalized[1], normalized[2]
    n_before = np.cross(b - a, c - a)
    n_after = np.cross(nb - na, nc - na)
    np.testing.assert_allclose(n_after / np.linalg.norm(n_after), n_before / np.linalg.norm(n_before), atol=1e-12)
    np.testing.assert_array_equal(normalize_to_unit_ball(np.array([[1.0, 2.0, 3.0]])), np.zeros((1, 3)))
    np.testing.assert_array_equal(normalize_to_unit_ball(np.ones((4, 3))), np.zeros((4, 3)))
    assert normalize_to_unit_ball(np.zeros((0, 3))).shape == (0, 3)


@pytest.mark.parametrize("method", ["organized", "pca"])
@pytest.mark.parametrize("case", ["empty", "all_nan", "one_point", "two_points", "some_nan_and_inf"])
def test_degenerate_clouds_give_finite_images(case, method):
    config = NormalImageConfig(normal_method=method)
    if case == "empty":
        points, shape = np.zeros((0, 3)), (0, 0)
    elif case == "all_nan":
        points, shape = np.full((12, 3), np.nan), (3, 4)
    elif case == "one_point":
        points, shape = np.array([[1.0, 0.0, 0.0]]), (1, 1)
    elif case == "two_points":
        points, shape = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), (1, 2)
    else:
        grid = tilted_plane_grid(10.0)
        grid[5:9] = np.nan
        grid[20, :, 2] = np.inf
        grid[30, 3] = [np.nan, 1.0, -np.inf]
        points, shape = grid.reshape(-1, 3), grid.shape[:2]
    image = cloud_to_normal_image(points, config, shape)
    assert image.shape == (128, 128) and image.dtype == np.float32
    assert np.isfinite(image).all() and image.min() >= 0.0 and image.max() <= 1.0
    if case == "some_nan_and_inf":
        covered = image > 0
        assert covered.mean() > 0.1
        np.testing.assert_allclose(image[covered], math.cos(math.radians(10.0)), atol=0.02)
    else:
        assert not image.any()


def test_organized_image_from_coordinates_is_the_whole_images_bit_for_bit():
    # Rows without a return above and below (the lidar's sky and chassis rows), a hole, an
    # inf: working on the band of rows with returns, by coordinate, changes nothing.
    grid = bench.lidar_depth_cloud(30, 45)
    grid[:7] = np.nan
    grid[-3:] = np.nan
    grid[12, 10:20] = np.nan
    grid[15, 4, 1] = np.inf
    points = grid.reshape(-1, 3)
    normals_z = estimate_normals_organized(grid)[..., 2].ravel()
    expected = normal_image(points, normals_z)
    assert (expected > 0).mean() > 0.1
    np.testing.assert_array_equal(organized_cloud_to_normal_image(points.T, grid.shape[:2]), expected)
    np.testing.assert_array_equal(cloud_to_normal_image(points, organized_shape=grid.shape[:2]), expected)
    # A PointCloud holds float32 coordinates.
    converter = NormalImageConverter(organized_shape=grid.shape[:2], R_BS=RotationMatrix())
    points_32 = points.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(
        converter.image_from_cloud(make_point_cloud(points)),
        cloud_to_normal_image(points_32, organized_shape=grid.shape[:2]),
    )


def test_organized_image_from_coordinates_checks_the_shape():
    with pytest.raises(ValueError, match=r"\(3, 12\).*\(3, 10\).*\(2, 5\)"):
        organized_cloud_to_normal_image(np.zeros((3, 12)), (2, 5))
    converter = NormalImageConverter(organized_shape=(2, 5))
    with pytest.raises(ValueError, match=r"\(3, 12\).*organized_shape \(2, 5\)"):
        converter.image_from_cloud(make_point_cloud(np.zeros((12, 3))))


def test_nan_normals_are_skipped():
    grid = tilted_plane_grid(0.0)
    points = grid.reshape(-1, 3)
    normals_z = np.ones(len(points))
    normals_z[::2] = np.nan
    image = normal_image(points, normals_z)
    assert np.isfinite(image).all() and image.max() == pytest.approx(1.0)
    assert not normal_image(points, np.full(len(points), np.nan)).any()


def test_wrong_shapes_raise():
    with pytest.raises(ValueError, match=r"\(5, 2\).*\(N, 3\)"):
        normal_image(np.zeros((5, 2)), np.zeros(5))
    with pytest.raises(ValueError, match=r"\(4,\).*\(5,\)"):
        normal_image(np.zeros((5, 3)), np.zeros(4))
    with pytest.raises(ValueError, match=r"\(5, 2\).*\(N, 3\)"):
        estimate_normals_pca(np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"\(4, 4, 2\).*\(H, W, 3\)"):
        estimate_normals_organized(np.zeros((4, 4, 2)))
    with pytest.raises(ValueError, match=r"\(3, 5\).*\(N, 3\)"):
        normalize_to_unit_ball(np.zeros((3, 5)))
    with pytest.raises(ValueError, match="organized_shape"):
        cloud_to_normal_image(np.zeros((6, 3)), NormalImageConfig(), (2, 2))
    with pytest.raises(ValueError, match="organized_shape"):
        cloud_to_normal_image(np.zeros((6, 3)), NormalImageConfig())
    with pytest.raises(ValueError, match="normal_method"):
        NormalImageConfig(normal_method="magic")
    with pytest.raises(ValueError, match="radius"):
        NormalImageConfig(radius=0.0)


def make_point_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> PointCloud:
    fields = BaseField.kXYZs | (BaseField.kNormals if normals is not None else 0)
    cloud = PointCloud(len(points), Fields(fields))
    cloud.mutable_xyzs()[:] = points.T
    if normals is not None:
        cloud.mutable_normals()[:] = normals.T
    return cloud


def test_converter_system_image_is_a_cached_function_of_the_cloud():
    grid = tilted_plane_grid(30.0)
    system = NormalImageConverter(organized_shape=grid.shape[:2])
    assert system.GetInputPort("point_cloud") is not None
    context = system.CreateDefaultContext()
    assert context.num_discrete_state_groups() == 0 and context.num_abstract_states() == 0
    output = system.GetOutputPort("normal_image")
    assert output.size() == 128 * 128
    system.GetInputPort("point_cloud").FixValue(context, PointCloud())
    assert not output.Eval(context).any()  # an empty cloud (before the lidar's first update)
    system.GetInputPort("point_cloud").FixValue(context, make_point_cloud(grid.reshape(-1, 3)))
    image = output.Eval(context)
    assert image.shape == (128 * 128,)
    covered = image > 0
    assert covered.mean() > 0.15
    np.testing.assert_allclose(image[covered], math.cos(math.radians(30.0)), atol=0.02)
    np.testing.assert_allclose(
        image.reshape(system.image_shape),
        cloud_to_normal_image(grid.reshape(-1, 3), organized_shape=grid.shape[:2]),
        atol=1e-6,
    )
    # The image depends on the cloud alone: time passing does not remake it, a new cloud does.
    made = []
    image_from_cloud = system.image_from_cloud

    def counting(cloud):
        made.append(cloud.size())
        return image_from_cloud(cloud)

    system.image_from_cloud = counting
    context.SetTime(0.35)
    np.testing.assert_array_equal(output.Eval(context), image)
    assert made == []
    system.GetInputPort("point_cloud").FixValue(context, make_point_cloud(tilted_plane_grid(10.0).reshape(-1, 3)))
    output.Eval(context)
    output.Eval(context)
    assert made == [grid.shape[0] * grid.shape[1]]


def test_converter_in_simulator_with_sensor_rotation_and_cloud_normals():
    grid = tilted_plane_grid(10.0)
    points_B = grid.reshape(-1, 3)
    # The same cloud in a camera-like frame S (+z forward, +x right, +y down).
    R_BS = RotationMatrix(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))
    points_S = points_B @ R_BS.matrix()
    system = NormalImageConverter(NormalImageConfig(normal_method="pca"), R_BS=R_BS)
    simulator = Simulator(system)
    context = simulator.get_mutable_context()
    system.GetInputPort("point_cloud").FixValue(context, make_point_cloud(points_S))
    simulator.AdvanceTo(robot.CONTROL_PERIOD_S / 2)
    image = system.GetOutputPort("normal_image").Eval(context)
    covered = image > 0
    assert covered.mean() > 0.15
    np.testing.assert_allclose(image[covered], math.cos(math.radians(10.0)), atol=0.02)
    # The cloud's own normals (here all tilted 60 deg, in S) win over estimation.
    normal_B = RollPitchYaw(math.radians(60.0), 0.0, 0.0).ToRotationMatrix().matrix()[:, 2]
    normals_S = np.tile(R_BS.matrix().T @ normal_B, (len(points_S), 1))
    system.GetInputPort("point_cloud").FixValue(context, make_point_cloud(points_S, normals_S))
    simulator.AdvanceTo(1.5 * robot.CONTROL_PERIOD_S)
    image = system.GetOutputPort("normal_image").Eval(context)
    np.testing.assert_allclose(image[image > 0], 0.5, atol=1e-5)


def test_converter_needs_organized_shape():
    with pytest.raises(ValueError, match="organized_shape"):
        NormalImageConverter()
    system = NormalImageConverter(NormalImageConfig(normal_method="pca"))
    context = system.CreateDefaultContext()
    system.GetInputPort("point_cloud").FixValue(context, PointCloud())
    assert not system.GetOutputPort("normal_image").Eval(context).any()


def test_benchmark_runs():
    result = bench.measure_normal_image_ms(points_count=600, repeats=1)
    assert set(result) >= {"normal_image_organized_ms", "normal_image_pca_ms"}
    assert all(value > 0 for value in result.values())
