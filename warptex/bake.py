"""Baking a solid texture onto a mesh: vertex colors and UV textures (Dong 2008, 6.2).

The solid texture is queried at surface points in voxel space (one unit = one finest
voxel); a 4x4 transform places the mesh in the block of matter (see
``warptex.surface.block_transform``). Only voxels around the surface get synthesized.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Protocol

import numpy as np
import trimesh
import warp as wp
from PIL import Image
from scipy import ndimage

from kernels import bake as _k
from warptex.device import device as default_device
from warptex.device import init_warp, launch
from warptex.exemplar import reencoded
from warptex.sheets import to_rgb, to_rgb8
from warptex.surface import to_voxel_space
from warptex.texture import SolidTexture, query_slabs


class PointTexture(Protocol):
    def query(self, points: np.ndarray, filter: str = ...) -> np.ndarray: ...


def vertex_colors(texture: SolidTexture, mesh: trimesh.Trimesh, transform: np.ndarray,
                  filter: str = "trilinear", progress: str | None = None) -> np.ndarray:
    """Colors (V, C) of the solid texture at each vertex, under a progress bar named
    ``progress`` if given."""
    return query_slabs(texture, to_voxel_space(mesh, transform), filter, progress)


def texel_points(
    mesh: trimesh.Trimesh, uv: np.ndarray, transform: np.ndarray, size: tuple[int, int],
    device: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (H*W, 3) float64 in voxel space shown by each texel, and which texels
    any triangle covers. ``size`` is (width, height)."""
    init_warp()
    dev = device or default_device()
    width, height = size
    faces = wp.array(np.asarray(mesh.faces, np.int32), dtype=wp.vec3i, device=dev)
    uv_wp = wp.array(np.asarray(uv, np.float32), dtype=wp.vec2, device=dev)
    owner = wp.full(width * height, _k.NO_TRIANGLE, dtype=wp.int32, device=dev)
    launch(_k.claim_texels, len(mesh.faces), [uv_wp, faces, width, height], [owner],
           device=dev)
    points = wp.zeros(width * height, dtype=wp.vec3d, device=dev)
    positions = wp.array(to_voxel_space(mesh, transform), dtype=wp.vec3d, device=dev)
    launch(_k.texel_points, width * height, [uv_wp, positions, faces, owner, width, height],
           [points], device=dev)
    return points.numpy(), owner.numpy() != _k.NO_TRIANGLE


def bake_uv_texture(
    texture: PointTexture, mesh: trimesh.Trimesh, uv: np.ndarray, transform: np.ndarray,
    size: int = 1024, filter: str = "trilinear",
) -> tuple[np.ndarray, np.ndarray]:
    """A (size, size, C) image: each covered texel shows the solid texture at its surface
    point; uncovered texels take the nearest covered color so filtering does not bleed
    background into the seams. Also returns the coverage mask."""
    points, covered = texel_points(mesh, uv, transform, (size, size))
    colors = texture.query(points[covered], filter=filter)
    image = np.zeros((size * size, colors.shape[1]), np.float32)
    image[covered] = colors
    image = image.reshape(size, size, -1)
    mask = covered.reshape(size, size)
    if mask.any() and not mask.all():
        _, (iy, ix) = ndimage.distance_transform_edt(~mask, return_indices=True)
        image = image[iy, ix]
    return image, mask


VERTEX_COLOR_FORMATS = (".ply", ".glb")
_GLB_COLOR = "_linear_color"  # a mesh attribute trimesh writes as it is: float, VEC3
UV_TEXTURE_FORMATS = (".glb", ".obj")


def _matte(suffix: str, image: Image.Image | None,
           name: str) -> trimesh.visual.material.Material:
    """A white, matte material showing ``image`` (or the vertex colors) as baked: trimesh's
    default tints textures with 0.4 gray, and glTF's default material is metallic."""
    if suffix == ".glb":
        return trimesh.visual.material.PBRMaterial(
            name=name, baseColorTexture=image, metallicFactor=0.0, roughnessFactor=1.0)
    return trimesh.visual.material.SimpleMaterial(
        image=image, name=name, diffuse=[255] * 4, ambient=[255] * 4, specular=[0, 0, 0, 255])


def _float_color_0(tree: dict) -> None:
    """Name the float colors :func:`export` gives a glTF file its ``COLOR_0``: glTF's vertex
    colors are linear, and trimesh writes ``COLOR_0`` in 8 bits, which band the darks
    (a dark sRGB gradient kept 10 of its 47 levels)."""
    for mesh in tree.get("meshes", []):
        for primitive in mesh["primitives"]:
            attributes = primitive["attributes"]
            if _GLB_COLOR in attributes:
                attributes["COLOR_0"] = attributes.pop(_GLB_COLOR)


def exported_files(path: str | Path, *, uv_texture: bool) -> list[Path]:
    """The files :func:`export` writes for ``path``: an OBJ with a UV texture comes with its
    material library and its PNG texture, named after it."""
    path = Path(path)
    if uv_texture and path.suffix.lower() == ".obj":
        return [path, path.with_suffix(".mtl"), path.with_suffix(".png")]
    return [path]


def export(mesh: trimesh.Trimesh, path: str | Path, *, colors: np.ndarray | None = None,
           image: np.ndarray | None = None, uv: np.ndarray | None = None,
           srgb: bool | None = None) -> list[Path]:
    """Write a textured mesh atomically: PLY/GLB with vertex ``colors``, or GLB (embedded
    PNG) / OBJ (+ MTL + PNG, :func:`exported_files`) with a UV ``image``. Returns the files
    written.

    ``srgb``: whether the colors are sRGB-encoded (``Exemplar.srgb``), so that each file
    holds what its readers assume: PNG textures and PLY vertex colors sRGB-encoded, glTF
    vertex colors linear (glTF 2.0, ``COLOR_0``); None writes them as they are.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    options: dict = {}
    attributes: dict[str, np.ndarray] = {}
    if image is not None:
        if suffix not in UV_TEXTURE_FORMATS:
            raise ValueError(f"{path}: a UV texture needs a .glb or .obj file")
        if srgb is not None:
            image = reencoded(image, srgb=srgb, to_srgb=True)
        material = _matte(suffix, Image.fromarray(to_rgb8(image)), path.stem)
        visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    elif colors is not None:
        if suffix not in VERTEX_COLOR_FORMATS:
            raise ValueError(f"{path}: vertex colors need a .ply or .glb file")
        if srgb is not None:
            colors = reencoded(colors, srgb=srgb, to_srgb=suffix != ".glb")
        rgb = to_rgb(colors.reshape(-1, 1, colors.shape[1])).reshape(-1, 3)
        if suffix == ".glb":  # COLOR_0 beside a material, else glTF's default is metallic
            visual = trimesh.visual.TextureVisuals(material=_matte(suffix, None, path.stem))
            attributes[_GLB_COLOR] = rgb
            options["tree_postprocessor"] = _float_color_0
        else:
            rgb8 = to_rgb8(rgb[:, None, :])[:, 0]
            rgba = np.c_[rgb8, np.full(len(rgb8), 255, np.uint8)]
            visual = trimesh.visual.ColorVisuals(vertex_colors=rgba)
    else:
        raise ValueError("nothing to export: give colors or an image")
    out = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, visual=visual,
                          vertex_attributes=attributes, process=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.name}.") as tmp:
        staged = Path(tmp) / path.name
        if suffix == ".obj":
            options["mtl_name"] = f"{path.stem}.mtl"
        out.export(staged, **options)
        written = []
        for f in sorted(Path(tmp).iterdir()):
            target = path.parent / f.name
            os.replace(f, target)
            written.append(target)
    return written
