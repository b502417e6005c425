"""Baking a solid texture onto a mesh: vertex colors and UV textures (Dong 2008, 6.2).

The solid texture is queried at surface points in voxel space (one unit = one finest
voxel); a 4x4 transform places the mesh in the block of matter (see
``warptex.surface.block_transform``). Only voxels around the surface get synthesized.
"""

from __future__ import annotations

import numpy as np
import trimesh
import warp as wp
from scipy import ndimage

from kernels import bake as _k
from warptex.settings import Filter, check_count
from warptex.surface import checked_faces, to_voxel_space
from warptex.synthesis import engine_device
from warptex.texture import PointTexture, query_slabs
from warptex.warp_runtime import launch


def vertex_colors(texture: PointTexture, mesh: trimesh.Trimesh, transform: np.ndarray,
                  filter: Filter = "trilinear", progress: str | None = None) -> np.ndarray:
    """Colors (V, C) of the solid texture at each vertex, as the texture gives them
    (``texture.srgb`` says their encoding: ``mesh_files.export(..., srgb=)`` writes each
    format's), under a progress bar named ``progress`` if given."""
    return query_slabs(texture, to_voxel_space(mesh, transform), filter, progress)


def texel_points(
    mesh: trimesh.Trimesh, uv: np.ndarray, transform: np.ndarray, size: tuple[int, int],
    device: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (H*W, 3) float64 in voxel space shown by each texel, and which texels
    any triangle covers. ``size`` is (width, height)."""
    width, height = (check_count("size", side, 1) for side in size)
    faces_np = checked_faces(mesh)
    uv = _checked_uv(uv, len(mesh.vertices), faces_np)
    dev = engine_device(device)
    faces = wp.array(faces_np, dtype=wp.vec3i, device=dev)
    uv_wp = wp.array(uv, dtype=wp.vec2, device=dev)
    owner = wp.full(width * height, _k.NO_TRIANGLE, dtype=wp.int32, device=dev)
    launch(_k.claim_texels, len(mesh.faces), [uv_wp, faces, width, height], [owner],
           device=dev)
    points = wp.zeros(width * height, dtype=wp.vec3d, device=dev)
    positions = wp.array(to_voxel_space(mesh, transform), dtype=wp.vec3d, device=dev)
    launch(_k.texel_points, width * height, [uv_wp, positions, faces, owner, width, height],
           [points], device=dev)
    return points.numpy(), owner.numpy() != _k.NO_TRIANGLE


def _checked_uv(uv: object, vertices: int, faces: np.ndarray) -> np.ndarray:
    """``uv`` as float32 (V, 2), a row per one of the mesh's ``vertices``, finite where its
    ``faces`` read it, else a ValueError: the kernels read it at them, unchecked."""
    try:
        uv = np.asarray(uv, np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"uv must be an array of numbers, got {type(uv).__name__}") from error
    if uv.shape != (vertices, 2):
        raise ValueError(f"uv must hold one (u, v) row per mesh vertex, ({vertices}, 2), got "
                         f"shape {uv.shape}")
    if not np.isfinite(uv[faces]).all():  # unused vertices' are never read
        raise ValueError("uv holds NaN or infinite coordinates")
    return uv.astype(np.float32)


# Share of the UV area that may differ from the texels covered without overlap: texel
# centres sample each triangle's area, more or less by a row along the layout's outlines.
_OVERLAP_SLACK = 0.05
_UV_SLACK = 1e-4  # of the texture's side: far below one texel of any texture baked
_COLLAPSED_AREA = 1e-12  # of the texture's: a millionth of a texel of a 1024^2 texture
_DEGENERATE_SHARE = 1e-6  # of the median face's area: a face of less has no surface to show


def unwrapped(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` with UVs made by xatlas, its vertices split along the UV seams, as
    ``Trimesh.unwrap`` gives it, but unwrapped at unit size around the origin: xatlas works
    in float32, in which a mesh at map coordinates (1e5 units out) collapsed to faces of no
    UV area and one a few millimetres across to NaN UVs. The vertices are the mesh's own."""
    import xatlas
    from trimesh.visual import TextureVisuals

    faces = checked_faces(mesh)
    vertices = np.asarray(mesh.vertices, np.float64)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    extent = float((high - low).max()) or 1.0
    vmap, faces, uv = xatlas.parametrize((vertices - (low + high) / 2) / extent, faces)
    return trimesh.Trimesh(vertices=vertices[vmap], faces=faces,
                           visual=TextureVisuals(uv=uv), process=False)


def uv_layout_problems(uv: np.ndarray, faces: np.ndarray, covered: np.ndarray,
                       areas: np.ndarray | None = None) -> list[str]:
    """What makes a mesh's own UVs bake colors that are not its surface's: triangles reaching
    outside [0, 1] (tiled UVs), whose parts outside no texel holds, triangles whose UV
    images overlap (mirrored or shared UVs), whose surface points share texels that show one
    of them, and triangles whose UVs have no area (collapsed, as exporters leave faces they
    did not map), which no texel shows. ``covered`` is :func:`bake_uv_texture`'s coverage
    mask; ``areas``, the faces' surface areas where given, leaves out faces of none."""
    uv = np.asarray(uv, np.float64)
    corners = uv[np.asarray(faces)]
    problems = []
    sides = corners[:, 1:] - corners[:, :1]
    uv_area = 0.5 * np.abs(sides[:, 0, 0] * sides[:, 1, 1] - sides[:, 0, 1] * sides[:, 1, 0])
    collapsed = uv_area <= _COLLAPSED_AREA
    if areas is not None:  # float rounding leaves a collinear face a hair of area
        areas = np.asarray(areas, np.float64)
        typical = np.median(areas[areas > 0]) if (areas > 0).any() else np.inf
        collapsed &= areas > _DEGENERATE_SHARE * typical
    if collapsed.any():
        problems.append(f"the UVs of {collapsed.sum()} of {len(faces)} triangles have no area "
                        "(collapsed, as for faces an exporter did not map): no texel shows "
                        "their surface")
    # Exporters' float32 rounding leaves UVs of a layout in [0, 1] a hair outside it.
    outside = ((corners < -_UV_SLACK) | (corners > 1.0 + _UV_SLACK)).any(axis=(1, 2))
    if outside.any():
        problems.append(f"the UVs of {outside.sum()} of {len(faces)} triangles reach outside "
                        "[0, 1] (tiled UVs), where no texel holds their colors")
    area = uv_area[~outside].sum()
    shown = covered.mean()
    if area > shown * (1 + _OVERLAP_SLACK):
        problems.append(f"{1 - shown / area:.0%} of the UV area lies over other triangles' "
                        "(mirrored or shared UVs), whose surface points then share texels")
    return problems


def bake_uv_texture(
    texture: PointTexture, mesh: trimesh.Trimesh, uv: np.ndarray, transform: np.ndarray,
    size: int = 1024, filter: Filter = "trilinear",
) -> tuple[np.ndarray, np.ndarray]:
    """A (size, size, C) image: each covered texel shows the solid texture at its surface
    point; uncovered texels take the nearest covered color so filtering does not bleed
    background into the seams. Also returns the coverage mask."""
    size = check_count("size", size, 1)
    points, covered = texel_points(mesh, uv, transform, (size, size))
    colors = texture.query(points[covered], filter=filter)
    del points  # 24 bytes a texel, not to be held through the filling below
    image = np.zeros((size * size, colors.shape[1]), np.float32)
    image[covered] = colors
    image = image.reshape(size, size, -1)
    mask = covered.reshape(size, size)
    if mask.any() and not mask.all():
        # The distances, float64 and unused, would double the fill's memory.
        iy, ix = ndimage.distance_transform_edt(~mask, return_distances=False,
                                                return_indices=True)
        image = image[iy, ix]
    return image, mask
