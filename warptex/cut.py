"""Planar cuts of textured objects (Dong 2008, section 6.4, Fig. 1b and 1d).

Because the solid texture is spatially deterministic, the new surfaces a cut exposes are
textured on demand and continue the texture of the outer surface without seams.
"""

from __future__ import annotations

import warnings

import numpy as np
import shapely
import trimesh
from tqdm.auto import tqdm

from warptex.mesh_files import checked_mesh


def cut(mesh: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray,
        progress: bool = False) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """Split a mesh by a plane into two halves, each closed by a planar cap.

    The first half lies on the side ``normal`` points to. Each cap is refined (see
    :func:`_refined_cap`) to twice the median length of the mesh's edges that cross the
    plane, so that vertex colours resolve the texture on it about as on the surface around
    it, and it still meets the outer surface vertex for vertex. Both halves' caps are the
    same triangles, so a point of the cut face shows one colour on either; where they are
    not, or a closed mesh got no cap, a UserWarning says so. A plane that
    passes within 1e-7 of the mesh's size of a vertex, not through it, is moved off it by
    about that much. ``progress`` shows a bar over the two halves (seconds each for a mesh
    of a few hundred thousand faces).
    """
    mesh = checked_mesh(mesh)
    normal, origin = _plane_vector("normal", normal), _plane_vector("origin", origin)
    if not np.abs(normal).max() > 0:
        raise ValueError("the cut plane needs a non-zero normal")
    # Scaled by its largest component first: its length alone overflows beyond 1e154.
    normal = normal / np.abs(normal).max()
    normal /= np.linalg.norm(normal)
    # Triangles of zero area bound nothing, and the cap's triangulation fails on them.
    kept = mesh.area_faces > 0
    if not kept.any():
        raise ValueError("every triangle of the mesh has zero area")
    if not kept.all():
        mesh = mesh.submesh([kept], append=True, repair=False)
    # trimesh slices within absolute tolerances (1e-8): cut at about unit size and near the
    # origin, where rounding stays far below them. Both steps are exact for the mesh's own
    # vertices (see _unit_frame), which the halves keep bit for bit.
    centre, scale = _unit_frame(mesh.vertices)
    unit = trimesh.Trimesh((mesh.vertices - centre) * scale, mesh.faces, process=False)
    origin = _clear_plane(unit.vertices, (origin - centre) * scale, normal)
    # How dense the surface is where the plane cuts it: its edges that cross the plane.
    above = (unit.vertices - origin) @ normal > 0
    crossing = above[unit.edges_unique[:, 0]] != above[unit.edges_unique[:, 1]]
    if not crossing.any():
        raise ValueError("the plane does not cut the mesh")
    spacing = 2.0 * float(np.median(unit.edges_unique_length[crossing]))
    sides = (normal, -normal)
    sliced = [trimesh.intersections.slice_mesh_plane(unit, side, origin, cap=True)
              for side in sides]
    if any(half is None or len(half.faces) == 0 for half in sliced):
        raise ValueError("the plane does not cut the mesh")
    _share_section(*sliced, origin, normal)
    refined = []
    # A loop, not a comprehension: Python 3.11 gives a comprehension a frame of its own,
    # and _refined_cap's warning would point at this line instead of the caller's.
    for half, side in tqdm(list(zip(sliced, sides, strict=True)), desc="cutting", unit="half",
                           disable=not progress):
        refined.append(_refined_cap(half, origin, side, spacing))
    _warn_of_unshared_caps(refined, origin, normal, unit)
    first, second = (trimesh.Trimesh(half.vertices / scale + centre, half.faces, process=False)
                     for half in refined)
    return first, second


def _plane_vector(name: str, value: object) -> np.ndarray:
    """``value`` as a finite float64 3-vector, else a ValueError naming the argument."""
    try:
        vector = np.asarray(value, np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"the cut plane's {name} must be three numbers, got {value!r}") from error
    if vector.shape != (3,) or not np.isfinite(vector).all():
        raise ValueError(f"the cut plane's {name} must be three finite numbers, got {value!r}")
    return vector


def _warn_of_unshared_caps(halves: list[trimesh.Trimesh], origin: np.ndarray,
                           normal: np.ndarray, mesh: trimesh.Trimesh) -> None:
    """Warn where the two halves' caps are not the same triangles, so that a point of the
    cut face may show another colour on either half (a cap left unrefined, a plane along one
    of the mesh's faces, a self-intersecting mesh), or where the ``mesh`` they were cut from,
    closed (every edge held by two faces or more), was left without one (walls inside it)."""
    caps = [{frozenset(map(bytes, triangle))
             for triangle in half.vertices[half.faces[cap_faces(half, origin, normal)]]}
            for half in halves]
    if not caps[0] and not caps[1]:
        if len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)):
            return  # open: cut where it has no inside
        warnings.warn("the cut left both halves of a closed mesh open: no outline in the "
                      "plane bounds a cap (walls inside the mesh?)", stacklevel=3)
    elif caps[0] != caps[1]:
        shared = len(caps[0] & caps[1])
        warnings.warn(f"the two halves' caps differ ({shared} of {len(caps[0])} and "
                      f"{len(caps[1])} triangles shared: a cap left unrefined, a plane along "
                      "one of the mesh's faces, through its opening or a self-intersection): "
                      "a point of the cut face may show another colour on either half",
                      stacklevel=3)


def _unit_frame(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """A centre and a power-of-two scale that bring ``vertices`` to about unit size near
    the origin, both exactly: the centre is zero on an axis where the mesh is not far from
    the origin for its size, else within a quarter of its coordinates there, so that their
    differences with it are exact (Sterbenz), and so is adding it back."""
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    size = max(float((high - low).max()), 1e-300)
    middle = (low + high) / 2
    centre = np.where(np.abs(middle) > 4 * size, middle, 0.0)
    return centre, 2.0 ** -np.ceil(np.log2(size))


def _share_section(first: trimesh.Trimesh, second: trimesh.Trimesh, origin: np.ndarray,
                   normal: np.ndarray) -> None:
    """Give the vertices of ``second``'s section the coordinates of ``first``'s: trimesh
    finds where the plane crosses an edge from the edge's end on each half's side, points
    apart in their last bits, and the caps are to be triangulated from the same points."""
    from warptex import parallel

    ours, theirs = (np.flatnonzero(_in_plane(h, origin, normal, _CAP_TOLERANCE))
                    for h in (first, second))
    if not len(ours) or not len(theirs):
        return
    distance, nearest = parallel.nearest(parallel.kd_tree(first.vertices[ours]),
                                         second.vertices[theirs])
    same = distance <= _CAP_TOLERANCE * max(float(np.ptp(first.vertices, axis=0).max()), 1e-300)
    vertices = second.vertices.copy()
    vertices[theirs[same]] = first.vertices[ours[nearest[same]]]
    second.vertices = vertices


# Vertices closer to the cut plane than this (of a mesh of unit size) but off it by more
# than rounding (_ON_PLANE) are taken as on it by trimesh's slicing (within 1e-8) and off it
# by the cap's test, or near enough for the slicing to add a second vertex beside them: the
# cap breaks. The cap's own test (_CAP_TOLERANCE, of the half's size) allows for rounding.
_PLANE_CLEARANCE = 1e-7
_ON_PLANE = 1e-12
_CAP_TOLERANCE = 1e-10


def _clear_plane(vertices: np.ndarray, origin: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """``origin`` moved along the unit ``normal`` by the least that leaves no vertex of a
    mesh of about unit size within ``_PLANE_CLEARANCE`` of the plane, where one lies that
    near without lying on it up to rounding; unmoved otherwise (a plane through vertices,
    as through a cylinder's axis, is cut there)."""
    distance = (vertices - origin) @ normal
    near = distance[np.abs(distance) < 1e3 * _PLANE_CLEARANCE]
    if not ((np.abs(near) > _ON_PLANE) & (np.abs(near) < _PLANE_CLEARANCE)).any():
        return origin
    offsets = np.concatenate([near - 1.01 * _PLANE_CLEARANCE, near + 1.01 * _PLANE_CLEARANCE])
    clear = (np.abs(near[None, :] - offsets[:, None]) >= _PLANE_CLEARANCE).all(axis=1)
    if not clear.any():  # vertices everywhere near the plane: nothing better to do
        return origin
    offsets = offsets[clear]
    return origin + offsets[np.argmin(np.abs(offsets))] * normal


def _refined_cap(half: trimesh.Trimesh, origin: np.ndarray, side: np.ndarray,
                 max_edge: float) -> trimesh.Trimesh:
    """``half`` (the part of a mesh on the side ``side`` points to) with its cap
    triangulated anew: trimesh triangulates a cap from its outline alone, in slivers that
    span it, so vertex colours would only interpolate the outline's. The cap becomes the
    constrained Delaunay triangulation of the outer surface's outline vertices, refined by
    :func:`_bisect_long_edges` until no edge of it is longer than ``max_edge``.
    """
    in_plane = _in_plane(half, origin, side, _CAP_TOLERANCE)
    cap = in_plane[half.faces].all(axis=1)  # cap_faces, from the vertices found once
    if not cap.any():  # an open mesh cut where it has no inside
        return half
    # One frame for both halves (the normal's sign made positive in its first non-zero
    # component), so that both triangulate the same points alike and their caps match.
    n = side / np.linalg.norm(side)
    facing = np.sign(n[np.flatnonzero(n)[0]])
    n = n * facing
    e1 = np.cross(n, np.eye(3)[np.argmin(np.abs(n))])
    e1 /= np.linalg.norm(e1)
    uv = (half.vertices - origin) @ np.stack([e1, np.cross(n, e1)], axis=1)
    # The outline: the edges in the plane that only one face of the outer surface holds,
    # and those of trimesh's cap that close an open mesh's section across its opening. Not
    # the cap's other edges: where the plane crosses a flat quad's diagonal, they skip the
    # middle one of three collinear outline vertices, and the cap would leave a crack there.
    # A region built from them keeps every outline vertex, where a union of triangles
    # drops collinear ones.
    count = len(uv)
    section = _boundary_keys(half.faces[~cap], count)
    section = section[in_plane[_edge_ends(section, count)].all(axis=1)]
    ends = np.bincount(_edge_ends(section, count).ravel(), minlength=count) < 2
    closing = np.setdiff1d(_boundary_keys(half.faces[cap], count), section)
    closing = closing[ends[_edge_ends(closing, count)].all(axis=1)]
    outline = _edge_ends(np.concatenate([section, closing]), count)
    region = shapely.build_area(shapely.union_all(shapely.linestrings(_in_order(uv[outline]))))
    triangles = shapely.get_parts(shapely.constrained_delaunay_triangles(region))
    corners = shapely.get_coordinates(triangles).reshape(len(triangles), 4, 2)[:, :3]
    index = {uv[i].tobytes(): i for i in np.unique(outline)}
    faces = np.array([index.get(c.tobytes(), -1) for c in corners.reshape(-1, 2)]).reshape(-1, 3)
    # The outline's closed loops: an open mesh may also cross the plane in open chains,
    # which bound nothing.
    points = np.unique([index.get(c.tobytes(), -1) for c in shapely.get_coordinates(region)])
    if (len(faces) == 0 or (faces < 0).any() or not np.array_equal(np.unique(faces), points)
            or not np.isin(half.faces[cap], points).all()):
        warnings.warn("a cut's cap could not be refined; its colors interpolate its outline's",
                      stacklevel=3)
        return half
    # A cap faces away from its half, against ``side``: clockwise in (e1, e2), whose normal
    # n is ``side`` times ``facing``.
    flip = _winding(uv, faces) * facing > 0
    faces[flip] = faces[flip][:, ::-1]
    faces = np.concatenate([half.faces[~cap], faces])
    refine = np.arange(len(faces)) >= (~cap).sum()
    near = _with_neighbours(faces, refine)
    vertices, refined = _bisect_long_edges(half.vertices, faces[near], refine[near], max_edge)
    return trimesh.Trimesh(vertices, np.concatenate([faces[~near], refined]), process=False)


def _bisect_long_edges(vertices: np.ndarray, faces: np.ndarray, refine: np.ndarray,
                      max_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Longest-edge bisection (Rivara): each face ``refine`` with an edge longer than
    ``max_edge`` is halved through its longest edge, until none is left. The other faces
    holding that edge are halved with it, so the mesh gains no T-junctions; ``faces`` must
    therefore hold every neighbour of the faces ``refine``. Returns the vertices (the given
    ones first) and the faces.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    refine = np.asarray(refine, bool)
    while True:
        keys, ids = np.unique(_edge_keys(faces, len(vertices)), return_inverse=True)
        edges = _edge_ends(keys, len(vertices))
        ids = ids.reshape(-1, 3)
        rank, length = _rank_edges(vertices, edges)
        longest = rank[ids].argmax(axis=1)
        chosen = np.where(refine & (length[ids].max(axis=1) > max_edge),
                          ids[np.arange(len(faces)), longest], -1)
        if (chosen < 0).all():
            return vertices, faces
        # A face outside ``refine`` goes along with the highest-ranked edge offered to it;
        # an edge is split where every face holding it agrees, so a face splits once a round.
        offered = np.zeros(len(edges), bool)
        offered[chosen[chosen >= 0]] = True
        outside = np.where(offered[ids], rank[ids], -1)
        local = np.where(refine, longest, outside.argmax(axis=1))
        chosen = np.where(refine | (outside.max(axis=1) < 0), chosen,
                          ids[np.arange(len(faces)), local])
        holders = np.bincount(ids.ravel(), minlength=len(edges))
        agree = np.bincount(chosen[chosen >= 0], minlength=len(edges))
        split = offered & (agree == holders)
        midpoint = np.full(len(edges), -1)
        midpoint[split] = len(vertices) + np.arange(split.sum())
        vertices = np.concatenate([vertices, vertices[edges[split]].mean(axis=1)])
        halved = (chosen >= 0) & split[np.maximum(chosen, 0)]
        f, k = faces[halved], local[halved]
        rows = np.arange(len(f))
        a, b, c = f[rows, k], f[rows, (k + 1) % 3], f[rows, (k + 2) % 3]
        m = midpoint[chosen[halved]]
        faces = np.concatenate([faces[~halved], np.stack([a, m, c], 1), np.stack([m, b, c], 1)])
        refine = np.concatenate([refine[~halved], refine[halved], refine[halved]])


def _rank_edges(vertices: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each edge's rank by length, ties broken by where it lies (its midpoint, then its
    direction, along a direction of no symmetry of a mesh), not by its index: the two
    halves of a cut number their cap's vertices apart, and must still bisect it alike.
    Also the lengths."""
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    order = np.argsort(length, kind="stable")
    # Only the runs of equal lengths are sorted again (few, but all of a symmetric cap's).
    tied = length[order[1:]] == length[order[:-1]]
    runs = np.flatnonzero(np.r_[False, tied] | np.r_[tied, False])
    if len(runs):
        along = vertices @ _TIE_DIRECTION
        members = order[runs]
        a, b = along[edges[members, 0]], along[edges[members, 1]]
        # A run starts where a member's length differs from the one before it.
        run = np.cumsum(np.r_[True, ~tied[runs[1:] - 1]])
        order[runs] = members[np.lexsort((np.abs(b - a), a + b, run))]  # either way round
    rank = np.empty(len(edges), np.int64)
    rank[order] = np.arange(len(edges))
    return rank, length


_TIE_DIRECTION = np.array([0.5773502691896258, 0.3141592653589793, 0.7536116385232097])


def _in_order(segments: np.ndarray) -> np.ndarray:
    """2D ``segments`` (E, 2, 2), each from its lesser end (by u, then v), sorted: an
    order that does not depend on the vertices' numbering, for the triangulation to
    break its ties (cocircular points) alike on both halves of a cut."""
    swap = np.lexsort((segments[:, :, 1], segments[:, :, 0]), axis=1)[:, 0] == 1
    segments = np.where(swap[:, None, None], segments[:, ::-1], segments)
    flat = segments.reshape(len(segments), 4)
    return segments[np.lexsort(flat.T[::-1])]


def _winding(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """+1 where a triangle of 2D points turns counter-clockwise, -1 where clockwise."""
    (ax, ay), (bx, by), (cx, cy) = (uv[faces[:, k]].T for k in range(3))
    return np.sign((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))


def _with_neighbours(faces: np.ndarray, selected: np.ndarray) -> np.ndarray:
    """``selected`` grown by the faces sharing an edge with it."""
    keys = _edge_keys(faces, int(faces.max()) + 1)
    return selected | np.isin(keys, keys[selected]).any(axis=1)


def _edge_keys(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """(F, 3) int64 keys of each face's edges (its vertices 0-1, 1-2, 2-0), the same for
    both orientations of an edge: lower vertex * ``vertex_count`` + higher vertex."""
    ends = np.sort(np.asarray(faces, np.int64)[:, [[0, 1], [1, 2], [2, 0]]], axis=2)
    return ends[..., 0] * vertex_count + ends[..., 1]


def _boundary_keys(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """The keys (:func:`_edge_keys`) of the edges that only one of ``faces`` holds."""
    keys, holders = np.unique(_edge_keys(faces, vertex_count), return_counts=True)
    return keys[holders == 1]


def _edge_ends(keys: np.ndarray, vertex_count: int) -> np.ndarray:
    """The (E, 2) vertices of edge ``keys``; the inverse of :func:`_edge_keys`."""
    return np.stack(np.divmod(keys, vertex_count), axis=1)


def cap_faces(half: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Which faces of a half that :func:`cut` made lie in its cut plane (the cap), found as
    the cut finds them."""
    return _in_plane(half, origin, normal, _CAP_TOLERANCE)[half.faces].all(axis=1)


def _in_plane(half: trimesh.Trimesh, origin: np.ndarray, normal: np.ndarray,
              tolerance: float) -> np.ndarray:
    """Which vertices of a cut half lie in the cut plane, within ``tolerance`` of the
    half's size."""
    normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    dist = (half.vertices - np.asarray(origin, np.float64)) @ normal
    scale = max(float(np.ptp(half.vertices, axis=0).max()), 1e-12)
    return np.abs(dist) <= tolerance * scale
