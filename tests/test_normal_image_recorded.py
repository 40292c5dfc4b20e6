"""The surface-normal image of recorded lidar clouds, bit for bit as the code before its speed-up made it.

tests/data/normal_image_recorded.npz holds six organized clouds that the `NormalImageConverter`
received in a learned rollout (`ditch-drake evaluate --env wide --task 1 --seed 300`, control
steps `rollout_steps`; float32 (3, H * W), as `PointCloud.xyzs()` hands them over) and the images
that `ditch_drake.perception.normal_image` made of them before its speed-up (commit af325cb): with
the default config, with the clouds turned 90 degrees about z (the grid's rows then reach the
image border), with another config (grid, radius, extent, `idw_power` 1.5), and through
`normal_image` with given normals. The speed-ups must not change a bit.

The images depend on the centroid that BLAS sums (`points @ ones`); the file keeps the centroids
of the machine that recorded it, and a machine whose BLAS sums them in another order skips the
bit-for-bit comparison rather than failing it. The other config's inverse-distance weights are a
float32 power 1.5, which numpy computes with the CPU's vector instructions, so its last bits
differ between CPUs (by up to 5 units in the last place between two Xeons): that image is
compared to within `MAX_ULP_OTHER_CPU` units in the last place; the default config's power 2 is
exact on every CPU and its images bit for bit.
"""

from pathlib import Path

import numpy as np
import pytest

from ditch_drake.perception.normal_image import (
    NormalImageConfig,
    cloud_to_normal_image,
    estimate_normals_organized,
    organized_cloud_to_normal_image,
)

RECORDED = Path(__file__).parent / "data" / "normal_image_recorded.npz"
OTHER_CONFIG = NormalImageConfig(rows=96, cols=112, radius=0.06, idw_power=1.5, x_min=-0.9, y_max=0.8)
MAX_ULP_OTHER_CPU = 8


@pytest.fixture(scope="module")
def recorded():
    data = dict(np.load(RECORDED))
    for cloud, centroid in zip(data["clouds"], data["centroids"]):
        points = cloud.astype(np.float64)
        points = points[:, np.isfinite(points[0] + points[1] + points[2])]
        if not np.array_equal(points @ np.ones(points.shape[1]) / points.shape[1], centroid):
            pytest.skip("this machine's BLAS sums a cloud's centroid in another order than the recording's")
    return data


def test_recorded_clouds_are_what_the_converter_gets(recorded):
    assert recorded["clouds"].dtype == np.float32
    assert recorded["clouds"].shape[1:] == (3, int(np.prod(recorded["organized_shape"])))


@pytest.mark.parametrize(
    ("images", "turn", "config"),
    [("images", False, NormalImageConfig()), ("images_turned", True, NormalImageConfig()),
     ("images_other_config", False, OTHER_CONFIG)],
)
def test_organized_images_of_recorded_clouds_are_unchanged_bit_for_bit(recorded, images, turn, config):
    shape = tuple(recorded["organized_shape"])
    for cloud, expected in zip(recorded["clouds"], recorded[images]):
        if turn:
            cloud = np.stack([cloud[1], -cloud[0], cloud[2]])
        image = organized_cloud_to_normal_image(cloud, shape, config)
        assert image.dtype == expected.dtype
        if config.idw_power == 2.0:
            assert np.array_equal(image, expected)
        else:
            np.testing.assert_array_max_ulp(image, expected, maxulp=MAX_ULP_OTHER_CPU)
        # The (N, 3) entry point takes the same path.
        assert np.array_equal(cloud_to_normal_image(cloud.T, config, shape), image)


def test_images_from_given_normals_are_unchanged_bit_for_bit(recorded):
    shape = tuple(recorded["organized_shape"])
    for cloud, expected in zip(recorded["clouds"], recorded["images_given_normals"]):
        points = cloud.T.astype(np.float64)
        normals = estimate_normals_organized(points.reshape(*shape, 3)).reshape(-1, 3)
        assert np.array_equal(cloud_to_normal_image(points, NormalImageConfig(), normals=normals), expected)
