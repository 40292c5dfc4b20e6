"""The surface-normal image (paper section 3.1; docs/design.md, "The observation"), in plain numpy/scipy.

The lidar's cloud becomes a 128 x 128 image whose pixels are the z component of the
terrain's surface normals: 1 on level ground, cos(t) on a slope of t, 0 on a vertical
wall and where no point is in reach. The steps follow the paper: normalize the cloud
into the unit ball; estimate a normal for every point, oriented up (+z); project the
points to the x-y plane; lay a regular grid over it; each pixel is the inverse-distance
weighted mean of the normals' z components of the points within a radius of its grid
point.

Normalizing scales x, y and z alike, so it does not turn normals: they are estimated on
the metric cloud and reused on the normalized one, and a plane tilted by t reads cos(t).

Image layout (for an input cloud in a frame with +x forward, +y left, +z up, e.g. the
robot's body frame B): pixel (row r, column c) sits at the grid point

    x = x_max - r * (x_max - x_min) / (rows - 1)
    y = y_max - c * (y_max - y_min) / (cols - 1)

of the normalized x-y plane: row 0 is farthest ahead (+x), column 0 leftmost (+y). Shown
with row 0 at the top, the image is the terrain ahead seen from above, forward up and
left on the left. Flattened, it is row-major (index r * cols + c).

Two normal estimators:
- `estimate_normals_organized`: the fast path for an organized cloud (the pixels of a
  depth image), from the cross product of differences to pixel neighbours.
- `estimate_normals_pca`: the reference, principal component analysis of the k nearest
  neighbours (any cloud).

NaN, inf, empty and one-point clouds give all-zero images. A cloud with coordinates beyond
2^256 (squares of which would overflow) is scaled down by a power of two first, so it gives
the image of the same cloud at a usable scale rather than overflowing.
"""

import functools
import math
import threading
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# The paper's image is N x M = 128 x 128 (section 3.1).
IMAGE_SHAPE = (128, 128)
NORMAL_METHODS = ("organized", "pca")
DEFAULT_PCA_K = 12
# The inverse distances are softened to 1 / (d^2 + (s * spacing)^2)^(p/2), with s this
# fraction of the grid spacing, so that a point on a grid point does not take it over alone.
_IDW_SOFTENING = 0.25

# Per-thread scratch memory for the image's large temporaries, reused from call to call:
# fresh memory costs page faults, which on a virtual machine cost more than the arithmetic
# (about 2 ms an image, measured). It holds no results, only room; buffers over
# _SCRATCH_MAX_ELEMENTS (huge clouds) are not kept.
_SCRATCH = threading.local()
_SCRATCH_MAX_ELEMENTS = 1 << 22
# Clouds with a finite coordinate beyond this are scaled down by a power of two before any
# product: squared distances, covariances and cross products overflow near 1e154. Normals
# and the image do not depend on the cloud's scale, and metric clouds never come close, so
# their results are untouched (bit for bit).
_LARGEST_UNSCALED = 2.0**256


@dataclass
class NormalImageConfig:
    """How the surface-normal image is made (lengths in the unit ball's normalized units).

    Attributes:
        rows: image height N (grid points along x).
        cols: image width M (grid points along y).
        radius: neighbourhood radius around each grid point; points farther away do not
            contribute. The default is about 2.5 grid spacings of the default grid.
        x_min: grid extent along the normalized x axis (row rows - 1 sits at x_min).
        x_max: row 0 sits at x_max.
        y_min: column cols - 1 sits at y_min.
        y_max: column 0 sits at y_max.
        normal_method: "organized" (the cloud is the pixels of a depth image; fast) or
            "pca" (k-nearest-neighbour PCA; any cloud; the reference).
        pca_k: neighbours per point for "pca" (at least 3).
        idw_power: exponent p of the inverse-distance weights, about 1 / d^p (Shepard's
            modified weights, falling to 0 at the radius; see `_splat`).
        discontinuity_ratio: for "organized", a central difference is used only when the
            two one-sided differences' lengths differ by at most this factor; otherwise
            the shorter one is (it does not straddle a depth jump).
    """

    rows: int = IMAGE_SHAPE[0]
    cols: int = IMAGE_SHAPE[1]
    radius: float = 0.04
    x_min: float = -1.0
    x_max: float = 1.0
    y_min: float = -1.0
    y_max: float = 1.0
    normal_method: str = "organized"
    pca_k: int = DEFAULT_PCA_K
    idw_power: float = 2.0
    discontinuity_ratio: float = 3.0

    def __post_init__(self):
        if self.rows < 2 or self.cols < 2:
            raise ValueError(f"image shape ({self.rows}, {self.cols}) must be at least (2, 2)")
        if not self.radius > 0.0:
            raise ValueError(f"radius {self.radius} must be > 0")
        if not (self.x_max > self.x_min and self.y_max > self.y_min):
            raise ValueError(f"empty grid extent x [{self.x_min}, {self.x_max}], y [{self.y_min}, {self.y_max}]")
        if self.normal_method not in NORMAL_METHODS:
            raise ValueError(f"normal_method {self.normal_method!r} is not one of {NORMAL_METHODS}")
        if self.pca_k < 3:
            raise ValueError(f"pca_k {self.pca_k} must be >= 3")
        if not self.idw_power > 0.0:
            raise ValueError(f"idw_power {self.idw_power} must be > 0")
        if not self.discontinuity_ratio >= 1.0:
            raise ValueError(f"discontinuity_ratio {self.discontinuity_ratio} must be >= 1")

    @property
    def spacing(self) -> tuple[float, float]:
        """The grid spacing (dx between rows, dy between columns), normalized units."""
        return ((self.x_max - self.x_min) / (self.rows - 1), (self.y_max - self.y_min) / (self.cols - 1))


def _as_points(points, name: str = "points") -> np.ndarray:
    """Returns `points` as a float64 (N, 3) array; raises ValueError on another shape."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim == 1 and array.size == 0:
        return array.reshape(0, 3)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} has shape {array.shape}; expected (N, 3)")
    return array


def _finite_rows(points: np.ndarray) -> np.ndarray:
    """(N,) mask of the rows of an (N, 3) array with no NaN or inf (fast: a row sum is
    finite exactly when its entries are, short of overflow near 1e308)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return np.isfinite(points @ np.ones(3))


def _scaled_down(points: np.ndarray, extent: float) -> np.ndarray:
    """`points` as they are if `extent` (their largest finite |coordinate|) is at most
    `_LARGEST_UNSCALED`, else multiplied by the power of two that brings it into [0.5, 1)
    (exact: only the exponents change)."""
    if not extent > _LARGEST_UNSCALED:
        return points
    return np.ldexp(points, -math.frexp(extent)[1])


def _extent(points: np.ndarray) -> float:
    """The largest |coordinate| of finite points (0 for none)."""
    return float(max(points.max(), -points.min())) if points.size else 0.0


def normalize_to_unit_ball(points: np.ndarray) -> np.ndarray:
    """Moves a cloud's centroid to the origin and scales it to fit the unit ball.

    Args:
        points: (N, 3) points. Rows with a NaN or inf are left out of the centroid and
            the scale and come back as NaN.

    Returns:
        (N, 3) points, centroid at 0, largest norm 1 (the same scale on x, y and z).
        A single point or a cloud with no extent comes back as zeros.

    Raises:
        ValueError: `points` is not (N, 3).
    """
    points = _as_points(points)
    out = np.full_like(points, np.nan)
    finite = _finite_rows(points)
    if not finite.any():
        return out
    good = _scaled_down(points[finite], _extent(points[finite]))
    centered = good - good.mean(axis=0)
    scale = np.sqrt((centered * centered).sum(axis=1).max())
    out[finite] = centered / scale if scale > 0.0 else 0.0
    return out


def _orient_up(normals: np.ndarray) -> np.ndarray:
    """Flips the (..., 3) unit normals with n_z < 0, in place; returns them."""
    normals *= np.where(normals[..., 2:3] < 0.0, -1.0, 1.0)
    return normals


def estimate_normals_pca(points: np.ndarray, k: int = DEFAULT_PCA_K) -> np.ndarray:
    """Estimates unit normals by PCA of each point's k nearest neighbours (the reference).

    The normal is the eigenvector of the neighbourhood covariance with the smallest
    eigenvalue, oriented so that n_z >= 0.

    Args:
        points: (N, 3) points; rows with a NaN or inf are ignored.
        k: neighbours per point, itself included (at least 3; fewer when the cloud is smaller).

    Returns:
        (N, 3) unit normals; NaN for non-finite points, for clouds of fewer than 3 finite
        points and where the neighbourhood is degenerate (collinear or coincident points).

    Raises:
        ValueError: `points` is not (N, 3) or k < 3.
    """
    points = _as_points(points)
    if k < 3:
        raise ValueError(f"k {k} must be >= 3")
    normals = np.full_like(points, np.nan)
    finite = _finite_rows(points)
    good = points[finite]
    if len(good) < 3:
        return normals
    good = _scaled_down(good, _extent(good))
    _, index = cKDTree(good).query(good, k=min(k, len(good)))
    neighbours = good[index]
    centered = neighbours - neighbours.mean(axis=1, keepdims=True)
    covariance = np.einsum("nki,nkj->nij", centered, centered)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    estimate = _orient_up(eigenvectors[:, :, 0].copy())
    degenerate = eigenvalues[:, 1] <= 1e-12 * np.maximum(eigenvalues[:, 2], np.finfo(float).tiny)
    estimate[degenerate] = np.nan
    normals[finite] = estimate
    return normals


def _along(axis: int, start: int | None, stop: int | None) -> tuple[slice, ...]:
    """An index that slices `start:stop` along `axis` and keeps the axes before it whole."""
    return (slice(None),) * axis + (slice(start, stop),)


def _tangent(grid: np.ndarray, axis: int, ratio: float) -> np.ndarray:
    """Differences to the pixel neighbours along `axis` of a (3, H, W) grid (1: rows, 2: columns).

    Central where both neighbours are valid, about equally far (`ratio`) and the forward
    one is not the farther; otherwise the shorter valid one-sided difference (doubled when
    both are valid and about equally far: only its direction matters); NaN where neither
    neighbour is valid. The plan was central differences whenever both neighbours are
    about equally far; this is what every demonstration and model of the project was
    made with. On the lidar's clouds a fully central version changes the images little
    and brings them no closer to the PCA reference, so it is left so.
    """
    # The differences padded with a NaN step at both ends: forward and backward are then
    # two overlapping views of one array, with no copies.
    count = grid.shape[axis]
    padded_shape = list(grid.shape)
    padded_shape[axis] += 1
    padded = np.empty(padded_shape)
    padded[_along(axis, 0, 1)] = np.nan
    padded[_along(axis, count, count + 1)] = np.nan
    np.subtract(grid[_along(axis, 1, None)], grid[_along(axis, None, -1)], out=padded[_along(axis, 1, count)])
    steps_sq = padded[0] * padded[0]
    steps_sq += padded[1] * padded[1]
    steps_sq += padded[2] * padded[2]
    forward, backward = padded[_along(axis, 1, None)], padded[_along(axis, None, -1)]
    forward_sq, backward_sq = steps_sq[_along(axis - 1, 1, None)], steps_sq[_along(axis - 1, None, -1)]
    with np.errstate(invalid="ignore"):
        forward_ok = forward_sq > 0.0
        backward_ok = backward_sq > 0.0
        # Forward unless only backward is valid or backward is shorter.
        use_backward = backward_ok & ~(forward_ok & (forward_sq <= backward_sq))
        central = (
            forward_ok
            & backward_ok
            & (np.maximum(forward_sq, backward_sq) <= ratio * ratio * np.minimum(forward_sq, backward_sq))
        )
    tangent = np.where(use_backward, backward, forward)
    np.add(tangent, backward, out=tangent, where=central)
    return tangent


def _organized_normals_planar(grid: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """The cross product of the row and column tangents of a (3, H, W) grid (NaN in all
    three coordinates where a pixel has no return), and the inverse of its length, signed
    so that the normal it scales points up (n_z >= 0): NaN where the normal is undefined
    (see `estimate_normals_organized`)."""
    down = _tangent(grid, 1, ratio)
    right = _tangent(grid, 2, ratio)
    normals = np.empty_like(grid)
    np.subtract(down[1] * right[2], down[2] * right[1], out=normals[0])
    np.subtract(down[2] * right[0], down[0] * right[2], out=normals[1])
    np.subtract(down[0] * right[1], down[1] * right[0], out=normals[2])
    norm_sq = normals[0] * normals[0] + normals[1] * normals[1] + normals[2] * normals[2]
    scale_sq = (down * down).sum(axis=0) * (right * right).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        # Tangents at least 1e-6 rad from parallel; negative n_z flips the normal up.
        good = norm_sq > 1e-12 * scale_sq
        inverse_norm = np.where(good, np.copysign(1.0, normals[2]) / np.sqrt(norm_sq), np.nan)
    return normals, inverse_norm


def estimate_normals_organized(points_grid: np.ndarray, discontinuity_ratio: float = 3.0) -> np.ndarray:
    """Estimates unit normals of an organized cloud from its pixel neighbours (the fast path).

    The normal at a pixel is the cross product of its tangents along the rows and the
    columns: central differences of the neighbouring pixels, one-sided at the image
    border, next to pixels without a return, and across depth jumps (where the two
    one-sided differences' lengths differ by more than `discontinuity_ratio`).

    Args:
        points_grid: (H, W, 3) points, one per depth-image pixel; NaN (or inf) where the
            pixel has no return.
        discontinuity_ratio: see `NormalImageConfig.discontinuity_ratio`.

    Returns:
        (H, W, 3) unit normals oriented so that n_z >= 0; NaN where a pixel has no return,
        no valid neighbour along the rows or the columns, or parallel tangents.

    Raises:
        ValueError: `points_grid` is not (H, W, 3).
    """
    points_grid = np.asarray(points_grid, dtype=np.float64)
    if points_grid.ndim != 3 or points_grid.shape[2] != 3:
        raise ValueError(f"points_grid has shape {points_grid.shape}; expected (H, W, 3)")
    grid = np.array(np.moveaxis(points_grid, 2, 0), order="C")  # (3, H, W), a copy: planar is faster.
    np.copyto(grid, np.nan, where=~np.isfinite(grid[0] + grid[1] + grid[2]))
    normals, inverse_norm = _organized_normals_planar(grid, discontinuity_ratio)
    normals *= inverse_norm
    return np.moveaxis(normals, 0, 2)


@functools.lru_cache(maxsize=32)
def _stencil(dx: float, dy: float, radius: float) -> tuple[np.ndarray, np.ndarray, tuple[tuple[int, int], ...]]:
    """The grid points that can be within `radius` of a point, relative to its nearest one.

    Returns:
        The row and column offsets (-K..K, -L..L), and for each row offset k the first and
        last index into the column offsets that can be in reach: a point is at most half
        a spacing from its nearest grid point, so offset (k, l) is in reach only if
        ((|k| - 1/2)+ dx)^2 + ((|l| - 1/2)+ dy)^2 <= radius^2.
    """
    row_offsets = np.arange(-int(np.floor(radius / dx + 0.5)), int(np.floor(radius / dx + 0.5)) + 1)
    col_offsets = np.arange(-int(np.floor(radius / dy + 0.5)), int(np.floor(radius / dy + 0.5)) + 1)
    col_gap_sq = (np.maximum(np.abs(col_offsets) - 0.5, 0.0) * dy) ** 2
    spans = []
    for k in row_offsets:
        row_gap_sq = (max(abs(k) - 0.5, 0.0) * dx) ** 2
        within = np.nonzero(row_gap_sq + col_gap_sq <= radius**2)[0]
        spans.append((int(within[0]), int(within[-1])))
    row_offsets.flags.writeable = False
    col_offsets.flags.writeable = False
    return row_offsets, col_offsets, tuple(spans)


def _scratch(name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
    """An uninitialized array of `shape` in this thread's reusable scratch memory."""
    size = math.prod(shape)
    if size > _SCRATCH_MAX_ELEMENTS:
        return np.empty(shape, dtype=dtype)
    buffer = getattr(_SCRATCH, name, None)
    if buffer is None or buffer.size < size or buffer.dtype != dtype:
        buffer = np.empty(max(size, 1), dtype=dtype)
        setattr(_SCRATCH, name, buffer)
    return buffer[:size].reshape(shape)


def _splat(x: np.ndarray, y: np.ndarray, values: np.ndarray, config: NormalImageConfig) -> np.ndarray:
    """Inverse-distance weighted image of `values` at normalized (x, y) (see the module doc).

    Each point visits the grid points around its nearest one that can be within the
    radius (`_stencil`) and adds its weight and its weighted value to two per-pixel sums;
    the image is their ratio. The same as querying a k-d tree for the points in each
    pixel's ball, without per-pixel lists. The weights are Shepard's modified inverse
    distances w = (d^2 + e^2)^(-p/2) - (r^2 + e^2)^(-p/2) for d < r, else 0 (d the
    distance, r the radius, e a softening of a quarter grid spacing), which fall to 0
    continuously at the radius, so that a point entering or leaving it does not make a
    pixel jump.
    """
    rows, cols = config.rows, config.cols
    dx, dy = config.spacing
    row_offsets, col_offsets, spans = _stencil(dx, dy, config.radius)
    count = len(x)
    # Arrays are (offset, point): numpy is fast along a long last axis. The large ones are
    # float32 in scratch memory and updated in place.
    row_f = (config.x_max - x) * (1.0 / dx)
    col_f = (config.y_max - y) * (1.0 / dy)
    row0 = np.clip(np.rint(row_f), -rows, 2 * rows)
    col0 = np.clip(np.rint(col_f), -cols, 2 * cols)
    row_sq, row_index = _offset_distances_sq(row_offsets, row0, row_f, dx, rows, "row")
    col_sq, col_index = _offset_distances_sq(col_offsets, col0, col_f, dy, cols, "col")
    row_index *= cols
    # Squared distances and flat pixel indices of the (point, grid point) pairs: (S, N).
    pairs = sum(last - first + 1 for first, last in spans)
    weights = _scratch("weights", (pairs, count), np.float32)
    flat = _scratch("flat", (pairs, count), np.intp)
    start = 0
    for one_row_sq, one_row_index, (first, last) in zip(row_sq, row_index, spans):
        stop = start + last - first + 1
        np.add(col_sq[first : last + 1], one_row_sq, out=weights[start:stop])
        np.add(col_index[first : last + 1], one_row_index, out=flat[start:stop])
        start = stop
    softening_sq = (_IDW_SOFTENING * min(dx, dy)) ** 2
    weights += np.float32(softening_sq)
    if config.idw_power == 2.0:
        np.reciprocal(weights, out=weights)
    else:
        np.power(weights, np.float32(-0.5 * config.idw_power), out=weights)
    weights -= np.float32((config.radius**2 + softening_sq) ** (-0.5 * config.idw_power))
    # Both sums in one pass: a complex64 sum adds the real parts (the weights) and the
    # imaginary parts (the weighted values) as two float32 sums, in the same order, so it
    # gives the two sums of two separate passes bit for bit, at a little over the cost of one.
    terms = _scratch("terms", (pairs, count), np.complex64)
    parts = terms.view(np.float32).reshape(pairs, count, 2)
    np.maximum(weights, np.float32(0.0), out=parts[..., 0])
    np.multiply(parts[..., 0], values.astype(np.float32), out=parts[..., 1])
    sums = np.zeros(rows * cols, dtype=np.complex64)
    np.add.at(sums, flat.ravel(), terms.ravel())
    denominator, numerator = sums.real, sums.imag
    image = np.zeros(rows * cols, dtype=np.float32)
    np.divide(numerator, denominator, out=image, where=denominator > 0.0)
    return np.clip(image, 0.0, 1.0, out=image).reshape(rows, cols)


def _offset_distances_sq(
    offsets: np.ndarray, nearest: np.ndarray, position: np.ndarray, spacing: float, size: int, name: str
) -> tuple[np.ndarray, np.ndarray]:
    """Float32 squared distances (offset, point) along one axis from each point (`position`,
    in grid units; `nearest` its rounded value) to the grid lines `offsets` away from its
    nearest one, and their indices clipped into 0..size-1; inf where the line is off the grid."""
    distances_sq = np.add(
        (offsets * spacing).astype(np.float32)[:, None],
        ((nearest - position) * spacing).astype(np.float32),
        out=_scratch(f"{name}_sq", (len(offsets), len(position)), np.float32),
    )
    np.square(distances_sq, out=distances_sq)
    index = np.add(offsets[:, None], nearest.astype(np.intp), out=_scratch(f"{name}_index", distances_sq.shape, np.intp))
    # Only the offsets that take some point off the grid need the test (often none, at most
    # the outer few).
    lowest, highest = (int(nearest.min()), int(nearest.max())) if len(nearest) else (0, 0)
    for one_sq, one_index, offset in zip(distances_sq, index, offsets):
        if lowest + offset < 0 or highest + offset >= size:
            one_sq[(one_index < 0) | (one_index >= size)] = np.inf
            np.clip(one_index, 0, size - 1, out=one_index)
    return distances_sq, index


def normal_image(points: np.ndarray, normals_z: np.ndarray, config: NormalImageConfig | None = None) -> np.ndarray:
    """Makes the surface-normal image from points and their normals' z components.

    Args:
        points: (N, 3) metric points, +z up (see the module doc for the frame and layout).
            Rows with a NaN or inf are dropped.
        normals_z: (N,) z components of the points' unit normals; its absolute value is
            used (normals oriented up). Points whose value is NaN or inf are dropped after
            the normalization (they still count for the centroid and the scale).
        config: the grid; None: `NormalImageConfig()`.

    Returns:
        float32 (rows, cols) image in [0, 1]; 0 where no point is within the radius.
        Never NaN; all zeros for an empty cloud or one without usable points.

    Raises:
        ValueError: `points` is not (N, 3) or `normals_z` is not (N,).
    """
    config = config or NormalImageConfig()
    points = _as_points(points)
    normals_z = np.asarray(normals_z, dtype=np.float64)
    if normals_z.shape != (len(points),):
        raise ValueError(f"normals_z has shape {normals_z.shape}; expected ({len(points)},) for {len(points)} points")
    finite = _finite_rows(points)
    if not finite.all():
        points, normals_z = points[finite], normals_z[finite]
    if len(points) == 0:
        return np.zeros((config.rows, config.cols), dtype=np.float32)
    points = _scaled_down(points, _extent(points))
    centroid = np.ones(len(points)) @ points / len(points)
    return _image_of_finite_points(points.T, centroid, normals_z, config)


def _image_of_finite_points(
    coordinates: np.ndarray, centroid: np.ndarray, normals_z: np.ndarray, config: NormalImageConfig
) -> np.ndarray:
    """`normal_image` of finite points given as (3, N) coordinates (x, y, z rows), and their centroid."""
    # normalize_to_unit_ball, on coordinate rows (faster than on points).
    centered = coordinates - centroid[:, None]
    x, y, z = centered
    scale = math.sqrt(float((x * x + y * y + z * z).max()))
    scale = 1.0 / scale if scale > 0.0 else 0.0
    values = np.abs(normals_z)
    use = np.isfinite(values)
    plane = centered[:2]
    if not use.all():
        plane, values = np.compress(use, plane, axis=1), values[use]
    plane *= scale
    return _splat(plane[0], plane[1], np.minimum(values, 1.0, out=values), config)


def organized_cloud_to_normal_image(
    xyzs: np.ndarray, organized_shape: tuple[int, int], config: NormalImageConfig | None = None
) -> np.ndarray:
    """`cloud_to_normal_image` with the "organized" method, for points stored by coordinate.

    The same image, bit for bit, from the layout of `PointCloud.xyzs()`, without turning
    it into rows of points and back. Only the image rows' band that holds returns is
    worked on: the lidar's upper rows often see nothing within range.

    Args:
        xyzs: (3, H * W) metric points, +z up, one column per depth-image pixel in
            row-major order; NaN (or inf) where a pixel has no return.
        organized_shape: (H, W).
        config: the grid and `discontinuity_ratio`; None: `NormalImageConfig()`.

    Returns:
        float32 (rows, cols) image in [0, 1], as `normal_image`.

    Raises:
        ValueError: `xyzs` is not (3, H * W).
    """
    config = config or NormalImageConfig()
    height, width = organized_shape
    xyzs = np.asarray(xyzs, dtype=np.float64)
    if xyzs.shape != (3, height * width):
        raise ValueError(
            f"xyzs has shape {xyzs.shape}; expected (3, {height * width}) for organized_shape {tuple(organized_shape)}"
        )
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf, or a sum past 1e308: not finite.
        finite = np.isfinite(xyzs[0] + xyzs[1] + xyzs[2])
    returned_rows = np.flatnonzero(finite.reshape(height, width).any(axis=1))
    if len(returned_rows) == 0:
        return np.zeros((config.rows, config.cols), dtype=np.float32)
    # Rows without a return are NaN, like the padding around the image, so the band's
    # normals are the whole image's.
    band = slice(returned_rows[0] * width, (returned_rows[-1] + 1) * width)
    in_band = finite[band]
    grid = np.where(in_band, xyzs[:, band], np.nan).reshape(3, -1, width)
    points = np.compress(in_band, grid.reshape(3, -1), axis=1)
    extent = _extent(points)
    grid, points = _scaled_down(grid, extent), _scaled_down(points, extent)
    normals, inverse_norm = _organized_normals_planar(grid, config.discontinuity_ratio)
    normals_z = np.multiply(normals[2], inverse_norm).ravel()
    centroid = points @ np.ones(points.shape[1]) / points.shape[1]
    return _image_of_finite_points(points, centroid, normals_z[in_band], config)


def cloud_to_normal_image(
    points: np.ndarray,
    config: NormalImageConfig | None = None,
    organized_shape: tuple[int, int] | None = None,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """Estimates the normals of a cloud (unless given) and makes its surface-normal image.

    Args:
        points: (N, 3) metric points, +z up; NaN (or inf) rows are points without a return.
        config: the grid and the normal method; None: `NormalImageConfig()`.
        organized_shape: (H, W) with H * W = N when the points are the pixels of a depth
            image in row-major order; required by the "organized" method.
        normals: optional (N, 3) normals to use instead of estimating them.

    Returns:
        float32 (rows, cols) image in [0, 1], as `normal_image`.

    Raises:
        ValueError: a shape is wrong, or the "organized" method lacks `organized_shape`.
    """
    config = config or NormalImageConfig()
    points = _as_points(points)
    if normals is not None:
        normals = _as_points(normals, "normals")
        if len(normals) != len(points):
            raise ValueError(f"normals has shape {normals.shape}; expected ({len(points)}, 3)")
    elif config.normal_method == "organized":
        if organized_shape is None:
            raise ValueError("normal_method 'organized' needs organized_shape=(H, W)")
        height, width = organized_shape
        if height * width != len(points):
            raise ValueError(f"organized_shape {tuple(organized_shape)} does not match {len(points)} points")
        return organized_cloud_to_normal_image(points.T, organized_shape, config)
    else:
        normals = estimate_normals_pca(points, config.pca_k)
    return normal_image(points, normals[:, 2], config)
