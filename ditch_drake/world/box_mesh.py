"""Boxes as one OBJ mesh: how the terrain's slabs (`DitchTerrain.box_pieces`) reach Meshcat
and the lidar's renderer as a few geometries instead of thousands.

SceneGraph's time to register a geometry grows with the geometries already in its frame, and
`RenderEngineVtk` costs 10-35 us per actor per image; a mesh per kind of piece costs neither.
"""

import numpy as np

# Which faces of the boxes a mesh keeps (`boxes_obj`).
FACE_CHOICES = ("top", "up", "all")

# Faces whose outward normal's world z is at most this face sideways or down: on terrain
# pieces seen from above they are buried in the neighbouring pieces.
UP_FACE_MIN_NORMAL_Z = 1e-3

# A unit cube's faces: outward normal and four corners (signs of x, y, z), counter-clockwise.
_CUBE_FACES = [
    ((1, 0, 0), [(1, -1, -1), (1, 1, -1), (1, 1, 1), (1, -1, 1)]),
    ((-1, 0, 0), [(-1, 1, -1), (-1, -1, -1), (-1, -1, 1), (-1, 1, 1)]),
    ((0, 1, 0), [(1, 1, -1), (-1, 1, -1), (-1, 1, 1), (1, 1, 1)]),
    ((0, -1, 0), [(-1, -1, -1), (1, -1, -1), (1, -1, 1), (-1, -1, 1)]),
    ((0, 0, 1), [(-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)]),
    ((0, 0, -1), [(-1, 1, -1), (1, 1, -1), (1, -1, -1), (-1, -1, -1)]),
]


def boxes_obj(boxes: list[tuple[np.ndarray, np.ndarray]], faces: str = "all") -> str:
    """OBJ text of boxes given as (size, X_WG as a 3 x 4 matrix), flat-shaded.

    `faces`: "all" keeps every face; "up" every face whose outward normal points up (world z
    above `UP_FACE_MIN_NORMAL_Z`), about a third of a terrain's triangles; "top" only each
    box's own +z face where it points up, a sixth: the terrain's pieces are slabs whose +z
    face is the ground's surface.

    Raises:
        ValueError: `faces` is not one of `FACE_CHOICES`.
    """
    if faces not in FACE_CHOICES:
        raise ValueError(f"faces={faces!r} must be one of {FACE_CHOICES}")
    signs = np.array([corners for _, corners in _CUBE_FACES], dtype=float)  # (6, 4, 3)
    normals = np.array([normal for normal, _ in _CUBE_FACES], dtype=float)  # (6, 3)
    sizes = np.array([size for size, _ in boxes])
    X = np.array([pose for _, pose in boxes])  # (n, 3, 4)
    corners = (
        np.einsum("nij,nfkj->nfki", X[:, :, :3], signs[None] * sizes[:, None, None, :] / 2) + X[:, None, None, :, 3]
    )
    face_normals = np.einsum("nij,fj->nfi", X[:, :, :3], normals)  # (n, 6, 3)
    keep = face_normals[..., 2] > (-np.inf if faces == "all" else UP_FACE_MIN_NORMAL_Z)
    if faces == "top":
        keep &= normals[:, 2] > 0
    corners, face_normals = corners[keep], face_normals[keep]  # (m, 4, 3), (m, 3)
    quads = 1 + 4 * np.arange(len(corners))[:, None] + np.arange(4)  # 1-based vertex indices
    k = np.arange(1, len(quads) + 1)
    triangles = np.stack([quads[:, 0], k, quads[:, 1], k, quads[:, 2], k, quads[:, 0], k, quads[:, 2], k,
                          quads[:, 3], k], axis=1)
    # One format string per block: the same text in a third of the time of line by line.
    return (("v %.6f %.6f %.6f\n" * len(corners) * 4) % tuple(corners.ravel().tolist())
            + ("vn %.6f %.6f %.6f\n" * len(face_normals)) % tuple(face_normals.ravel().tolist())
            + ("f %d//%d %d//%d %d//%d\nf %d//%d %d//%d %d//%d\n" * len(quads)) % tuple(triangles.ravel().tolist()))
