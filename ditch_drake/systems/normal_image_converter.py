"""The surface-normal image of the lidar's point cloud (paper 3.1), at the control rate."""

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RotationMatrix
from pydrake.perception import PointCloud
from pydrake.systems.framework import LeafSystem

from ditch_drake.perception.normal_image import (
    NormalImageConfig,
    cloud_to_normal_image,
    organized_cloud_to_normal_image,
)


class NormalImageConverter(LeafSystem):
    """Turns the lidar's point cloud into the 128 x 128 surface-normal image.

    The image is the output's cached value, computed when it is read and depending only on
    the `point_cloud` input: it is made once per new cloud (the lidar's update at the
    control rate), at the first read after it, and a read at any other time (a physics
    step, a later stage of the same control step) costs a cache lookup. The block has no
    state and no event of its own, so it adds no tick to the Simulator's schedule; whoever
    reads it (the frame stacker's update) sees the image of the lidar's newest cloud. An
    empty cloud (before the lidar's first update) gives all zeros. See
    `ditch_drake.perception.normal_image` for the method.

    .. pydrake_system::

        name: NormalImageConverter
        input_ports:
        - point_cloud
        output_ports:
        - normal_image

    Ports:
        point_cloud: a `pydrake.perception.PointCloud` in the sensor frame S (points
            without a return are NaN or inf). Only the rotation R_BS matters (the image
            is normalized about the cloud's centroid), so a cloud already in the robot's
            body frame B (+x forward, +y left, +z up) needs no `R_BS`. With
            `organized_shape=(H, W)` its H * W points are a depth image's pixels in
            row-major order.
        normal_image: rows * cols values in [0, 1], row-major: index r * cols + c is
            pixel (r, c); row 0 is farthest ahead (+x of B), column 0 leftmost (+y of
            B), so the image reshaped to (rows, cols) shows the terrain ahead from above,
            forward up. A pixel is the z component (in B) of the surface normals near its
            grid point, 0 where there is no point.
    """

    def __init__(
        self,
        config: NormalImageConfig | None = None,
        organized_shape: tuple[int, int] | None = None,
        R_BS: RotationMatrix | None = None,
        use_cloud_normals: bool = True,
    ):
        """Declares the ports.

        Args:
            config: the image and the normal estimator; None: `NormalImageConfig()`
                (128 x 128, organized normals).
            organized_shape: (H, W) of the depth image whose pixels the cloud's points
                are; required by the "organized" normal method.
            R_BS: rotation from the sensor frame S, in which the cloud arrives, to the
                body frame B with +z up; None: the identity (the cloud is in B).
            use_cloud_normals: use the cloud's own normals when it has them
                (`has_normals()`) instead of estimating them.

        Raises:
            ValueError: the "organized" method without `organized_shape`, or a shape
                that is not two positive integers.
        """
        super().__init__()
        self._config = config or NormalImageConfig()
        if organized_shape is not None:
            organized_shape = tuple(int(n) for n in organized_shape)
            if len(organized_shape) != 2 or min(organized_shape) < 1:
                raise ValueError(f"organized_shape {organized_shape} must be (H, W) with H, W >= 1")
        elif self._config.normal_method == "organized":
            raise ValueError(
                "normal_method 'organized' needs organized_shape=(H, W); "
                "use NormalImageConfig(normal_method='pca') for an unorganized cloud"
            )
        self._organized_shape = organized_shape
        # The identity (the lidar's frame is parallel to the body's) costs nothing.
        self._R_BS = None if R_BS is None or R_BS.IsExactlyIdentity() else R_BS.matrix()
        self._use_cloud_normals = use_cloud_normals
        self._cloud_port = self.DeclareAbstractInputPort("point_cloud", Value(PointCloud()))
        self.DeclareVectorOutputPort(
            "normal_image",
            self._config.rows * self._config.cols,
            self._calc_image,
            prerequisites_of_calc={self._cloud_port.ticket()},
        )

    @property
    def image_shape(self) -> tuple[int, int]:
        """(rows, cols) of the image that `normal_image` holds flattened row-major."""
        return (self._config.rows, self._config.cols)

    def image_from_cloud(self, cloud: PointCloud) -> np.ndarray:
        """The (rows, cols) float32 image of a cloud (what the update stores, unflattened).

        Raises:
            ValueError: a non-empty cloud whose size is not H * W of `organized_shape`
                while its normals are to be estimated by the "organized" method.
        """
        if cloud.size() == 0:
            return np.zeros(self.image_shape, dtype=np.float32)
        own_normals = self._use_cloud_normals and cloud.has_normals()
        if self._config.normal_method == "organized" and not own_normals:
            xyzs = cloud.xyzs() if self._R_BS is None else self._R_BS @ cloud.xyzs()
            return organized_cloud_to_normal_image(xyzs, self._organized_shape, self._config)
        points = np.ascontiguousarray(cloud.xyzs().T, dtype=np.float64)
        normals = None
        if own_normals:
            normals = np.ascontiguousarray(cloud.normals().T, dtype=np.float64)
        if self._R_BS is not None:
            points = points @ self._R_BS.T
            normals = None if normals is None else normals @ self._R_BS.T
        return cloud_to_normal_image(points, self._config, self._organized_shape, normals)

    def _calc_image(self, context, output) -> None:
        output.SetFromVector(self.image_from_cloud(self._cloud_port.Eval(context)).ravel())
