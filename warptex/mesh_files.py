"""Mesh files: meshes read as the commands read them (:func:`load_mesh`), and textured
meshes for other tools: vertex colors in PLY or glTF, UV textures in glTF or OBJ (+ MTL +
PNG), each in the color encoding its readers assume (Dong 2008, 6.2: the baked results of
``warptex.bake``)."""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Sequence
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import trimesh
from PIL import Image

from warptex.archive import input_file_problem, write_together
from warptex.settings import check_flag
from warptex.sheets import to_rgb, to_rgb8
from warptex.srgb import reencoded

MESH_FORMATS = ("ply", "obj", "glb", "gltf", "stl", "off")  # trimesh's common mesh formats
_WELD_TOLERANCE = 1e-8  # trimesh's tol.merge: vertices equal to 8 decimals are one
# trimesh welds vertices rounded to integers of the tolerance: kept above this share of their
# largest coordinate, so that those integers fit in int64 (beyond 1e11 units they overflowed).
_WELD_PRECISION = 1e-15
# Coordinates beyond this many units are refused: float64 vertices there lie an eighth of a
# unit apart or more, and welding's integers (at _WELD_PRECISION) would overflow int64.
_COORDINATE_LIMIT = 1e15
# .ply and .glb files hold vertices as float32 (glTF has no other; trimesh writes PLY so): a
# mesh whose vertices float32 would move by more than this share of its median edge, which
# bends and collapses its faces, is refused.
_FLOAT32_SHIFT = 1e-2
_TOLERANCE_LOCK = threading.Lock()
# MTL statements naming texture files (the file name last, after any options).
_MATERIAL_MAPS = ("map_ka", "map_kd", "map_ks", "map_ns", "map_d", "map_bump", "bump",
                  "disp", "decal", "refl", "norm", "map_pr", "map_pm", "map_ps", "map_ke")
VERTEX_COLOR_FORMATS = (".ply", ".glb")
_GLB_COLOR = "_linear_color"  # a mesh attribute trimesh writes as it is: float, VEC3
UV_TEXTURE_FORMATS = (".glb", ".obj")


class MeshFileError(ValueError):
    """A mesh file that cannot be read, or a mesh that cannot be written as asked; the
    message names the file."""


def checked_mesh(mesh: object) -> trimesh.Trimesh:
    """``mesh`` where it is a triangle mesh, else a TypeError saying where to get one:
    ``trimesh.load`` gives a Scene of a .glb or of an OBJ of several objects, on which
    warptex's functions failed deep inside (no attribute 'vertices')."""
    if isinstance(mesh, trimesh.Trimesh):
        return mesh
    where = ("load_mesh joins a file's objects into one mesh, as trimesh.load(..., force='mesh') "
             "does" if isinstance(mesh, trimesh.Scene) else "load_mesh reads one from a file")
    raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__} "
                    f"(warptex.mesh_files.{where})")


def weld_tolerance(vertices: np.ndarray) -> float:
    """How near vertices are welded into one: trimesh's 1e-8, or less for a mesh so small
    that this is over a millionth of its size, which would weld distinct vertices (a
    sphere 2e-8 units across, of 642 vertices, into 26)."""
    if not len(vertices):
        return _WELD_TOLERANCE
    size = _extent(vertices)
    tolerance = min(_WELD_TOLERANCE, 1e-6 * size) if size > 0 else _WELD_TOLERANCE
    return max(tolerance, _WELD_PRECISION * float(np.abs(vertices).max()))


def _extent(vertices: np.ndarray) -> float:
    """A mesh's size: the longest side of its bounding box, 0 without vertices."""
    return float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0


def load_mesh(path: str | Path, *, uv: str = "none", weld: bool = False,
              outputs: Sequence[str | Path] = ()) -> trimesh.Trimesh:
    """The mesh of file ``path`` as trimesh processes it (vertices that coincide welded,
    unless their normals or UVs differ; unused ones dropped, but in a .glb, where trimesh
    keeps them and nothing reads them), or with every coincident vertex welded (``weld``:
    a cut's caps need a closed surface, which flat-shaded faces with vertices of their own
    are not). ``uv="mesh"`` requires finite UVs of the file's faces;
    ``outputs`` are the files it is to be written to, of which a .ply or .glb is refused
    where float32 would move its vertices visibly.

    Raises:
        MeshFileError: anything of the above, or a file that is missing, unreadable, not a
            mesh, without triangles or area, or with NaN or far (beyond 1e15) vertices.
    """
    if uv not in ("none", "auto", "mesh"):
        raise ValueError(f"uv must be 'none', 'auto' or 'mesh', got {uv!r}")
    weld = check_flag("weld", weld)
    path = Path(path)
    problem = input_file_problem(path, "mesh file")
    if problem is not None:
        raise MeshFileError(f"{path}: {problem}")
    try:
        # As the file has it first: trimesh's processing drops the faces of a NaN vertex
        # unsaid, and loses the vertex normals that keep it from welding flat faces.
        raw = trimesh.load(path, force="mesh", process=False)
        used = _used_vertices(raw, path)
        if not np.isfinite(used).all():
            raise MeshFileError(f"{path}: vertex coordinates hold NaN or infinite values")
        farthest = float(np.abs(used).max()) if len(used) else 0.0
        if farthest > _COORDINATE_LIMIT:
            raise MeshFileError(f"{path}: vertex coordinates reach {farthest:.3g} units, "
                                f"beyond {_COORDINATE_LIMIT:.0e}: move the mesh nearer the "
                                "origin")
        # Loading processed keeps the file's normals and UVs apart as merging alone cannot;
        # trimesh welds at its global tolerance (its maintainer's advice is to set that).
        with _TOLERANCE_LOCK:  # a global of trimesh's: one load sets it at a time
            saved, trimesh.tol.merge = trimesh.tol.merge, weld_tolerance(used)
            try:
                # An unused NaN vertex, which processing drops, warns in its rounding first.
                with np.errstate(invalid="ignore"):
                    mesh = trimesh.load(path, force="mesh")
            finally:
                trimesh.tol.merge = saved
    except MeshFileError:
        raise
    except ImportError as error:  # a reader's optional library: the file may be sound
        raise MeshFileError(f"{path}: reading this format needs a library that is not "
                            f"installed ({error})") from None
    except NotImplementedError:  # how trimesh refuses a file type it has no reader for
        raise MeshFileError(f"{path}: not a mesh format warptex reads "
                            f"(.{', .'.join(MESH_FORMATS)}, and the others trimesh reads)"
                            ) from None
    except Exception as error:  # trimesh raises many kinds on a bad or unknown file
        raise MeshFileError(f"{path}: cannot read the mesh: damaged, or not what its name "
                            f"says (trimesh: {error or type(error).__name__})") from None
    if len(getattr(mesh, "faces", ())) == 0:
        raise MeshFileError(f"{path}: no triangles found")
    if weld:  # whatever their normals say
        digits = trimesh.util.decimal_to_digits(weld_tolerance(mesh.vertices))
        mesh.merge_vertices(merge_tex=True, merge_norm=True, digits_vertex=digits)
    if not mesh.area > 0:
        raise MeshFileError(f"{path}: every triangle has zero area: the mesh has no surface")
    if uv == "mesh" and getattr(mesh.visual, "uv", None) is None:
        raise MeshFileError(f"{path}: the mesh has no UVs; use --uv auto to make them")
    # A triangle with a NaN UV holds no texel: its surface would show its neighbours' colors.
    if uv == "mesh" and not np.isfinite(mesh.visual.uv[mesh.faces]).all():
        raise MeshFileError(f"{path}: UV coordinates hold NaN or infinite values; use --uv "
                            "auto to make UVs")
    _check_float32_outputs(mesh, [Path(o) for o in outputs])
    return mesh


def _used_vertices(raw: trimesh.Trimesh, path: Path) -> np.ndarray:
    """The vertices of the file's faces, as trimesh's processing keeps them: an unused
    vertex (far away, or NaN) must decide neither what is refused nor how near the used
    ones are welded. A negative index, which NumPy would wrap to the last vertices, is
    refused."""
    faces = np.asarray(getattr(raw, "faces", np.zeros((0, 3), np.int64)))
    if not len(faces):
        return np.zeros((0, 3))
    if faces.min() < 0:
        raise MeshFileError(f"{path}: a face refers to vertex {int(faces.min())}: damaged")
    return np.asarray(raw.vertices)[np.unique(faces)]


def _check_float32_outputs(mesh: trimesh.Trimesh, outputs: Sequence[Path]) -> None:
    """Refuse a .ply or .glb output of a mesh that float32 cannot hold: one far from the
    origin for its edges (a building at map coordinates) came out flattened, or with its
    small faces collapsed and turned, though it moved by a small part of its size."""
    narrow = [o for o in outputs if o.suffix.lower() in (".ply", ".glb")]
    if not narrow:
        return
    vertices = mesh.vertices
    corners = vertices[mesh.faces]
    lengths = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    edge = float(np.median(lengths[lengths > 0])) if (lengths > 0).any() else 0.0
    shift = float(np.abs(vertices.astype(np.float32) - vertices).max())
    if shift > _FLOAT32_SHIFT * edge:
        raise MeshFileError(f"{narrow[0]}: .ply and .glb files hold vertices as float32, which "
                            f"would move this mesh's by up to {shift:.3g}, {shift / edge:.2g} "
                            f"of its median edge (it lies {float(np.abs(vertices).max()):.3g} "
                            "from the origin): write .obj with a UV texture (--uv auto: .obj "
                            "holds no vertex colors), or move the mesh nearer the origin")


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


def referenced_files(path: str | Path) -> list[Path]:
    """The files a mesh file names that exist, which its readers load with it: an OBJ's
    material libraries and the textures they name, a .gltf's buffers and images. None where
    the file cannot be read as such (loading it says why)."""
    path = Path(path)
    suffix = path.suffix.lower()
    named: list[Path] = []
    try:
        if suffix == ".obj":
            # Several libraries to a line, as OBJ has it, or one name with spaces, as
            # trimesh reads it: whichever exist.
            for libraries in _statements(path, ("mtllib",)):
                for library in dict.fromkeys([libraries, *libraries.split()]):
                    named.append(path.parent / library)
                    if named[-1].is_file():
                        named += [named[-1].parent / _map_file(m)
                                  for m in _statements(named[-1], _MATERIAL_MAPS)]
        elif suffix == ".gltf":
            tree = json.loads(path.read_text(encoding="utf-8"))
            items = [item for kind in ("buffers", "images")
                     if isinstance(tree.get(kind), list) for item in tree[kind]]
            named += [path.parent / unquote(item["uri"]) for item in items
                      if isinstance(item, dict) and isinstance(item.get("uri"), str)
                      and not item["uri"].startswith("data:")]
    except (OSError, ValueError, AttributeError):
        return []
    return [p for p in named if p.exists()]


def _statements(path: Path, keywords: tuple[str, ...]) -> list[str]:
    """What follows each line of ``path`` that starts with one of ``keywords``, after any
    whitespace."""
    found = []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        word, *rest = line.split(None, 1)[:2] or [""]
        if word.lower() in keywords and rest and rest[0].strip():
            found.append(rest[0].strip())
    return found


def _map_file(statement: str) -> str:
    """The file an MTL texture statement names: the rest of its line, or its last word
    after options (``-s 2 2 1 wood.png``)."""
    return statement.split()[-1] if statement.startswith("-") else statement


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


def _obj_digits(vertices: np.ndarray) -> int:
    """Decimals an OBJ's numbers are written with: trimesh's 8 for a mesh a unit across or
    more, and one more per power of ten below, keeping a hundred-millionth of its size (one
    2e-9 across came out as a point)."""
    size = _extent(vertices)
    return 8 if size <= 0.0 else max(8, 8 - math.floor(math.log10(size)))


def _float_colors(name: str, values: object, shape: tuple[str, ...]) -> np.ndarray:
    """``values`` as colors of ``shape``'s axes, channels last, in [0, 1] as queries give
    them; an error naming ``name`` otherwise: 8-bit integers came out white, NaN black."""
    array = np.asarray(values)
    if not np.issubdtype(array.dtype, np.floating):
        raise TypeError(f"{name} must hold floats in [0, 1], as queries give them, got "
                        f"{array.dtype}")
    if array.ndim != len(shape) or array.shape[-1] == 0:
        raise ValueError(f"{name} must be a ({', '.join(shape)}) array, channels last, got "
                         f"shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} holds NaN or infinite values")
    return array


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

    ``colors`` (V, C) and ``image`` (H, W, C) are floats in [0, 1], as queries give them.
    ``srgb``: whether they are sRGB-encoded (``Exemplar.srgb``, ``SolidTexture.srgb``), so
    that each file holds what its readers assume: PNG textures and PLY vertex colors
    sRGB-encoded, glTF vertex colors linear (glTF 2.0, ``COLOR_0``); None writes them as
    they are, which a .glb's readers take for linear.
    """
    mesh = checked_mesh(mesh)
    path = Path(path)
    suffix = path.suffix.lower()
    options: dict = {}
    attributes: dict[str, np.ndarray] = {}
    colors = None if colors is None else _float_colors("colors", colors, ("V", "C"))
    image = None if image is None else _float_colors("image", image, ("H", "W", "C"))
    # trimesh writes arrays of another length without a word: gray, or no colors at all.
    for name, per_vertex in (("colors", colors), ("uv", uv)):
        if per_vertex is not None and len(per_vertex) != len(mesh.vertices):
            raise ValueError(f"{name} holds {len(per_vertex)} rows, one per vertex of the "
                             f"mesh's {len(mesh.vertices)}")
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
                                                        return_texture=True,
                                                        digits=_obj_digits(out.vertices))
    return [*((path.parent / name, companions[name]) for name in sorted(companions)),
            (path, text.encode())]
