"""Textured meshes for other tools: vertex colors in PLY or glTF, UV textures in glTF or
OBJ (+ MTL + PNG), each in the color encoding its readers assume (Dong 2008, 6.2: the
baked results of ``warptex.bake``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from warptex.archive import write_together
from warptex.exemplar import reencoded
from warptex.sheets import to_rgb, to_rgb8

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


def check_obj_name(path: str | Path) -> None:
    """A ValueError where an OBJ with a UV texture would be named with whitespace: its
    material library and texture take its name, on lines (``mtllib``, ``map_Kd``) that
    readers split at spaces."""
    path = Path(path)
    if path.suffix.lower() == ".obj" and any(c.isspace() for c in path.stem):
        raise ValueError(f"{path}: an .obj names its .mtl and texture after itself on lines "
                         "that readers split at spaces; choose a name without spaces "
                         "(or .glb)")


def export(mesh: trimesh.Trimesh, path: str | Path, *, colors: np.ndarray | None = None,
           image: np.ndarray | None = None, uv: np.ndarray | None = None,
           srgb: bool | None = None) -> list[Path]:
    """Write a textured mesh atomically (:func:`mesh_files`): PLY/GLB with vertex
    ``colors``, or GLB (embedded PNG) / OBJ (+ MTL + PNG, :func:`exported_files`) with a UV
    ``image``. Returns the files written."""
    files = mesh_files(mesh, path, colors=colors, image=image, uv=uv, srgb=srgb)
    write_files(files)
    return [f for f, _ in files]


def write_files(files: list[tuple[Path, bytes]]) -> None:
    """Write files and their contents together (``archive.write_together``): all of them,
    or, where one fails, none (the meshes of both halves of a cut among them)."""
    write_together([(f, lambda tmp, data=data: tmp.write_bytes(data)) for f, data in files])


def mesh_files(mesh: trimesh.Trimesh, path: str | Path, *, colors: np.ndarray | None = None,
               image: np.ndarray | None = None, uv: np.ndarray | None = None,
               srgb: bool | None = None) -> list[tuple[Path, bytes]]:
    """The files :func:`export` writes and their contents, an OBJ's material and texture
    before the OBJ, which is renamed into place last: it never arrives without them.

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
    if suffix != ".obj":
        return [(path, out.export(file_type=suffix[1:], **options))]
    check_obj_name(path)
    text, companions = trimesh.exchange.obj.export_obj(out, mtl_name=f"{path.stem}.mtl",
                                                        return_texture=True)
    return [*((path.parent / name, companions[name]) for name in sorted(companions)),
            (path, text.encode())]
