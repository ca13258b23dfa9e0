"""One convex hull per body part, in the part joint's local frame."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from embody.body.base import ConvexPiece

#: Half-thickness (m) given to parts too flat or small for a 3D hull.
THICKEN = 1e-4


def hull_piece(part: int, joint: int, local_points: np.ndarray) -> ConvexPiece:
    """Convex hull of points with unit outward planes (n, d): n·p + d ≤ 0 inside."""
    points = np.asarray(local_points, dtype=np.float64)
    try:
        hull = ConvexHull(points)
    except QhullError:  # flat or tiny part: thicken it by ±THICKEN so it still contains its points
        offsets = np.concatenate([np.eye(3), -np.eye(3)]) * THICKEN
        points = (points[:, None, :] + offsets[None]).reshape(-1, 3)
        hull = ConvexHull(points)
    return ConvexPiece(part=part, joint=joint, vertices=points[hull.vertices],
                       planes=np.ascontiguousarray(hull.equations))


def part_hulls(rest_vertices: np.ndarray, bind_positions: np.ndarray, part_joints: np.ndarray,
               vertex_parts: np.ndarray) -> list[ConvexPiece]:
    """Hull of each part's rest vertices relative to its joint (rest joints carry no rotation)."""
    return [hull_piece(i, int(j), rest_vertices[vertex_parts == i] - bind_positions[j])
            for i, j in enumerate(part_joints)]
