"""Texturing meshes: the voxels around a surface (Dong 2008, sections 6.2 and 6.4).

A mesh is placed in the solid texture by a 4x4 transform from its coordinates to voxel
space (one unit = one finest voxel). By default its bounding box is fitted into a
``resolution``^3 block, so the object looks carved from a block of that resolution.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh
import warp as wp

from kernels import surface as _k
from warptex.affine import apply_affine
from warptex.keysets import unique
from warptex.mesh_files import checked_mesh
from warptex.parallel import launch_ranges
from warptex.settings import check_count
from warptex.synthesis import COORD_LIMIT, engine_device

# Voxels a shell may hold: faces count the voxels they share each, which the int32 offsets
# of the touched voxels must hold too (a few times the shell on fine meshes).
MAX_SHELL = 1 << 28
# The kernel tests every voxel of a triangle's bounding box: a triangle whose box holds this
# many times more voxels than it can touch (a long sliver across the block, as CAD exports
# have) is halved first. One along the block's diagonal cost the cube of the resolution.
_BOX_WASTE = 64


def block_transform(mesh: trimesh.Trimesh, resolution: int) -> np.ndarray:
    """4x4 matrix fitting the mesh's bounding box, centred, into [0, resolution)^3."""
    resolution = check_count("resolution", resolution, 1)
    bounds = checked_mesh(mesh).bounds  # of the vertices its faces use: None without faces
    if bounds is None:
        raise ValueError("the mesh has no faces: no bounding box to fit")
    lo, hi = bounds
    extent = float(np.max(hi - lo))
    if extent <= 0:
        raise ValueError("the mesh has an empty bounding box")
    scale = (resolution - 1e-3) / extent
    m = np.eye(4)
    m[:3, :3] *= scale
    m[:3, 3] = resolution / 2.0 - scale * (lo + hi) / 2.0
    return m


def to_voxel_space(mesh: trimesh.Trimesh, transform: np.ndarray) -> np.ndarray:
    """Mesh vertices in voxel space, float64: far from the origin float32 would move them
    by up to half a voxel, so a baked vertex would not show the color a query of the same
    point gets."""
    v = np.asarray(checked_mesh(mesh).vertices, np.float64)
    m = _checked_transform(transform)
    # Not a matrix product: a BLAS sums its terms otherwise on other CPUs, and a vertex on
    # a voxel's border could land in another voxel there.
    return np.stack(apply_affine(m, *v.T), axis=1)


def _checked_transform(transform: object) -> np.ndarray:
    """``transform`` as a float64 4x4 matrix, else a ValueError naming it."""
    try:
        m = np.asarray(transform, np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"transform must be a 4x4 matrix of numbers, got "
                         f"{type(transform).__name__}") from error
    if m.shape != (4, 4):
        raise ValueError(f"transform must be a 4x4 matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError("transform holds NaN or infinite entries")
    return m


def checked_faces(mesh: trimesh.Trimesh) -> np.ndarray:
    """The mesh's faces as int32 (F, 3), after a ValueError unless each names one of its
    vertices: Warp's kernels read vertex arrays at them unchecked."""
    faces = np.asarray(checked_mesh(mesh).faces)
    if faces.size and (faces.min() < 0 or faces.max() >= len(mesh.vertices)):
        raise ValueError(f"the mesh's faces index vertices outside [0, {len(mesh.vertices)}), "
                         "the vertices it has")
    return faces.astype(np.int32).reshape(-1, 3)


def shell_size(mesh: trimesh.Trimesh, transform: np.ndarray) -> int:
    """About how many voxels :func:`shell` finds, from the geometry alone: the surface's
    area projected on the three axis planes, in voxels (a plane crosses that many; within
    0.1 % of the bunny's shell at resolutions 64 to 1024)."""
    v = to_voxel_space(mesh, transform)
    f = np.asarray(mesh.faces)
    doubled = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return int(np.abs(doubled).sum() / 2)


def checked_shell_size(mesh: trimesh.Trimesh, transform: np.ndarray) -> int:
    """:func:`shell_size`, or a ValueError when that is more than a shell may hold."""
    voxels = shell_size(mesh, transform)
    if voxels > MAX_SHELL:
        raise ValueError(f"the surface passes through about {voxels:.3g} voxels, more than "
                         f"the {MAX_SHELL} a shell may hold")
    return voxels


def shell(
    mesh: trimesh.Trimesh,
    resolution: int = 1024,
    transform: np.ndarray | None = None,
    device: str | None = None,
) -> np.ndarray:
    """The finest voxels (N, 3) int32 that the mesh surface passes through, sorted.

    ``transform`` maps mesh coordinates to voxel space; by default
    :func:`block_transform` for ``resolution``.
    """
    m = block_transform(mesh, resolution) if transform is None else _checked_transform(transform)
    faces_np = checked_faces(mesh)
    in_voxels = to_voxel_space(mesh, m)
    # As the kernel gets them, in float32, which may round a vertex onto the range's end
    # (or overflow, refused as well).
    with np.errstate(over="ignore"):
        reach = float(np.abs(in_voxels[faces_np].astype(np.float32)).max(initial=0.0))
    # The kernel's float-to-int voxel of a point beyond int32 is undefined (CPUs and GPUs
    # differ), and no voxel beyond the texture's range can be synthesized anyway.
    if not reach < COORD_LIMIT:  # NaN too
        raise ValueError(f"the transformed mesh reaches {reach:.3g} voxels from the origin, "
                         f"beyond the texture's +-{COORD_LIMIT}: check transform")
    checked_shell_size(mesh, m)
    dev = engine_device(device)
    vertices_np, faces_np = _slivers_halved(in_voxels, faces_np)
    # The shell only decides which voxels are synthesized ahead of the queries, so float32
    # suffices: a voxel it misses at extreme resolutions is synthesized when first read.
    vertices = wp.array(vertices_np.astype(np.float32), dtype=wp.vec3, device=dev)
    faces = wp.array(faces_np, dtype=wp.vec3i, device=dev)
    nfaces = len(faces_np)
    counts = wp.zeros(nfaces, dtype=wp.int32, device=dev)
    none = wp.empty(0, dtype=wp.vec3i, device=dev)
    # The counting pass: ``counts`` stands in for the offsets it does not read.
    launch_ranges(_k.touched_voxels, 0, nfaces, [vertices, faces, counts, 0], [counts, none],
                  device=dev)
    counts_np = counts.numpy()
    if counts_np.sum(dtype=np.int64) >= 2**31:  # the offsets below are int32
        raise ValueError(f"the surface touches {counts_np.sum(dtype=np.int64)} voxels "
                         f"counted face by face, more than a shell may hold")
    offsets = np.concatenate([[0], np.cumsum(counts_np)[:-1]]).astype(np.int32)
    voxels = wp.empty(int(counts_np.sum()), dtype=wp.vec3i, device=dev)
    launch_ranges(
        _k.touched_voxels,
        0,
        nfaces,
        [vertices, faces, wp.array(offsets, dtype=wp.int32, device=dev), 1],
        [counts, voxels],
        device=dev,
    )
    return _unique_rows(voxels.numpy())


def _slivers_halved(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The triangles of ``faces`` in voxel space, those whose bounding box the kernel would
    search mostly in vain halved across their longest edge until none is (appended with
    vertices of their own): together they cover the same surface, so they touch the same
    voxels. The arrays as given where no triangle needs it, as on meshes of even ones."""
    corners = vertices[faces]
    wasteful = _box_waste(corners)
    if not wasteful.any():
        return vertices, faces
    kept, pieces = [faces[~wasteful]], []
    corners = corners[wasteful]
    while len(corners):
        # Each triangle turned so that its longest edge runs from corner 0 to corner 1.
        lengths = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2)
        turn = (np.arange(3) + lengths.argmax(axis=1)[:, None]) % 3
        a, b, c = np.moveaxis(np.take_along_axis(corners, turn[:, :, None], axis=1), 1, 0)
        middle = (a + b) / 2
        corners = np.concatenate([np.stack([a, middle, c], axis=1),
                                  np.stack([middle, b, c], axis=1)])
        wasteful = _box_waste(corners)
        pieces.append(corners[~wasteful])
        corners = corners[wasteful]
    pieces = np.concatenate(pieces)
    first = len(vertices)
    added = first + np.arange(3 * len(pieces), dtype=np.int32).reshape(-1, 3)
    return (np.concatenate([vertices, pieces.reshape(-1, 3)]),
            np.concatenate([*kept, added]).astype(np.int32))


def _box_waste(corners: np.ndarray) -> np.ndarray:
    """Which triangles' (T, 3, 3) bounding boxes hold over ``_BOX_WASTE`` times the voxels
    they can touch: about their area projected on the three axis planes and their edges'
    lengths, a voxel or more each."""
    boxes = np.prod(np.floor(corners.max(axis=1)) - np.floor(corners.min(axis=1)) + 1, axis=1)
    edges = corners - np.roll(corners, -1, axis=1)
    touched = (np.abs(np.cross(edges[:, 0], edges[:, 1])).sum(axis=1) / 2
               + np.abs(edges).sum(axis=(1, 2)) + 1)
    return boxes > _BOX_WASTE * touched


def _unique_rows(voxels: np.ndarray) -> np.ndarray:
    """The distinct rows of integer ``voxels`` (N, 3), sorted: rows numbered within their
    bounding box, so one 1D sort does it (sorting rows directly is many times slower)."""
    if len(voxels) == 0:
        return np.zeros((0, 3), np.int32)
    lo = voxels.min(axis=0).astype(np.int64)
    span = voxels.max(axis=0).astype(np.int64) - lo + 1
    if math.prod(int(n) for n in span) >= 2**63:  # the box's numbers would wrap in int64
        return np.unique(voxels, axis=0).astype(np.int32)
    v = voxels.astype(np.int64) - lo
    keys = unique((v[:, 0] * span[1] + v[:, 1]) * span[2] + v[:, 2])
    rows = np.stack([keys // (span[1] * span[2]), keys // span[2] % span[1], keys % span[2]], 1)
    return (rows + lo).astype(np.int32)
