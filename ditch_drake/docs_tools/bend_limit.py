"""Measures the bend-radius limit of the ditch family (docs/concepts/terrain_family.md).

For sine and arc courses of several cross-sections it sweeps the tightest bend radius and
prints the largest |height - pieces_height| (m) on a 5 cm grid over the ditch (one half of
the course; both courses are symmetric), next to `min_bend_radius_m`:

    python -m ditch_drake.docs_tools.bend_limit

The courses use max_turn_deg = 2, so that the error of the polyline's facets (which grows
as max_turn_deg squared, about 4 cm at 6 degrees on a 55 degree wall) stays small beside
the fold this measures. Takes about a minute.
"""

import math

import numpy as np

from ditch_drake.world.terrain import FLAT_REACH_M, TerrainParams, _profile_width, _unchecked_terrain, min_bend_radius_m

SPACING_M = 0.05
MAX_TURN_DEG = 2.0
PROFILES = [  # bottom_width_m, depth_m, slope_deg (hinge and toe radii 0.5 m)
    (4.0, 4.0, 55.0),  # the packaged sine's
    (2.0, 2.5, 45.0),
    (8.0, 5.0, 60.0),
    (2.0, 5.0, 60.0),
    (8.0, 2.5, 45.0),
]


def sine_params(radius_m: float, wavelength_m: float = 30.0, **profile) -> TerrainParams:
    """One period of a sine whose tightest bend has the given radius (amplitude A = 1 / (R k^2))."""
    k = 2 * math.pi / wavelength_m
    return TerrainParams(course="sine", sine_amplitude_m=1 / (radius_m * k * k), sine_wavelength_m=wavelength_m,
                         length_m=wavelength_m, max_turn_deg=MAX_TURN_DEG, **profile)


def arc_params(radius_m: float, sweep_deg: float = 180.0, **profile) -> TerrainParams:
    return TerrainParams(course="arc", arc_radius_m=radius_m, length_m=radius_m * math.radians(sweep_deg),
                         max_turn_deg=MAX_TURN_DEG, **profile)


def max_error_m(params: TerrainParams, spacing_m: float = SPACING_M) -> float:
    """max |pieces_height - height| (m) over grid points (x >= -0.5) within the hinge + 0.3 m."""
    terrain = _unchecked_terrain(params)  # below the limit validate() refuses it
    low = terrain.course_xy.min(axis=0) - terrain.half_width_m - 0.5
    high = terrain.course_xy.max(axis=0) + terrain.half_width_m + 0.5
    xs, ys = np.arange(-0.5, high[0], spacing_m), np.arange(low[1], high[1], spacing_m)
    X, Y = np.meshgrid(xs, ys)
    flat = np.stack([X.ravel(), Y.ravel()], axis=1)
    d = np.concatenate([terrain.nearest_on_course(flat[i:i + 20000])[0] for i in range(0, len(flat), 20000)])
    d = d.reshape(X.shape)
    top = np.full(X.shape, -np.inf)
    # `pieces_height`, one piece at a time on the grid block under its top face.
    for piece in terrain.box_pieces():
        n = piece.R_WP[:, 2]
        if n[2] < 1e-6:
            continue
        c = piece.p_WP + n * piece.size[2] / 2
        half = piece.size[:2] / 2
        corners = c[:2] + np.array([[sx * half[0], sy * half[1]] for sx in (-1, 1) for sy in (-1, 1)]) @ piece.R_WP[:2, :2].T
        i0, i1 = (np.searchsorted(xs, [corners[:, 0].min() - 1e-6, corners[:, 0].max() + 1e-6]))
        j0, j1 = (np.searchsorted(ys, [corners[:, 1].min() - 1e-6, corners[:, 1].max() + 1e-6]))
        if i0 >= i1 or j0 >= j1:
            continue
        x, y = X[j0:j1, i0:i1], Y[j0:j1, i0:i1]
        z = c[2] - (n[0] * (x - c[0]) + n[1] * (y - c[1])) / n[2]
        local = np.stack([x - c[0], y - c[1], z - c[2]], axis=-1) @ piece.R_WP
        inside = (np.abs(local[..., 0]) <= half[0] + 1e-9) & (np.abs(local[..., 1]) <= half[1] + 1e-9)
        block = top[j0:j1, i0:i1]
        top[j0:j1, i0:i1] = np.where(inside, np.maximum(block, z), block)
    near = d < terrain.half_width_m + 0.3
    return float(np.max(np.abs(top - terrain.profile_height(d))[near]))


def main() -> None:
    print(f"max |height - pieces_height| (m), 5 cm grid, max_turn_deg={MAX_TURN_DEG:g}; "
          f"FLAT_REACH_M={FLAT_REACH_M:.3f}")
    print("| bottom, depth, slope | hinge (m) | course | limit (m) | R (m) | R - limit | error (m) |")
    print("|---|---|---|---|---|---|---|")
    for index, (bottom, depth, slope) in enumerate(PROFILES):
        profile = {"bottom_width_m": bottom, "depth_m": depth, "slope_deg": slope}
        hinge = bottom / 2 + _profile_width(TerrainParams(**profile))
        offsets = (0.5, 0.05, -0.1, -0.25, -0.5) if index == 0 else (0.05, -0.25)
        for course, make in (("sine", sine_params), ("arc 180", arc_params)):
            limit = min_bend_radius_m(make(10.0, **profile))
            for offset in offsets:
                radius = limit + offset
                error = max_error_m(make(radius, **profile))
                print(f"| {bottom:g}, {depth:g}, {slope:g} | {hinge:.2f} | {course} | {limit:.2f} | {radius:.2f} | "
                      f"{offset:+.2f} | {error:.3f} |", flush=True)


if __name__ == "__main__":
    main()
