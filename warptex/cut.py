"""Planar cuts of textured objects (Dong 2008, section 6.4, Fig. 1b and 1d).

Because the solid texture is spatially deterministic, the new surfaces a cut exposes are
textured on demand and continue the texture of the outer surface without seams.
"""

from __future__ import annotations

import numpy as np
import trimesh


def plane_points(origin: np.ndarray, u: np.ndarray, v: np.ndarray,
                 shape: tuple[int, int]) -> np.ndarray:
    """Points (H*W, 3) of a planar grid: pixel (r, c) lies at origin + r*u + c*v."""
    h, w = shape
    r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    origin, u, v = (np.asarray(a, np.float64) for a in (origin, u, v))
    pts = origin + r.reshape(-1, 1) * u + c.reshape(-1, 1) * v
    return pts.astype(np.float32)


def cut(mesh: trimesh.Trimesh, origin: np.ndarray,
        normal: np.ndarray) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """Split a mesh by a plane into two halves, each closed by a planar cap.

    The first half lies on the side ``normal`` points to.
    """
    normal = np.asarray(normal, np.float64)
    if not np.linalg.norm(normal) > 0:
        raise ValueError("the cut plane needs a non-zero normal")
    halves = []
    for side in (normal, -normal):
        half = trimesh.intersections.slice_mesh_plane(mesh, side, origin, cap=True)
        if half is None or len(half.faces) == 0:
            raise ValueError("the plane does not cut the mesh")
        halves.append(half)
    return halves[0], halves[1]


def cap_faces(half: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray,
              tolerance: float = 1e-6) -> np.ndarray:
    """Which faces of a cut half lie in the cut plane (the cap)."""
    normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    dist = (half.vertices[half.faces] - np.asarray(origin, np.float64)) @ normal
    scale = max(float(np.ptp(half.vertices, axis=0).max()), 1e-12)
    return (np.abs(dist) <= tolerance * scale).all(axis=1)
