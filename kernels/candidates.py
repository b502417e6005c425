"""Kernels of the 3D candidate pre-computation (Dong 2008, section 4).

Exemplar roles are cyclic: role 0 is the exemplar whose pixels own the candidate lists,
role 1 the next axis and role 2 the one after. An exemplar of role k spans the volume axes
(k+1, k+2) as its (first, second) coordinates, so role k and role k+1 share the volume
axis k+2: the second-coordinate strip of role k meets the first-coordinate strip of
role k+1. The three crossbar pairs are therefore (0, 1), (1, 2) and (2, 0).
"""

import warp as wp

from kernels.common import bit_mask, pixel_coords, pixel_index

wp.set_module_options({"enable_backward": False})

# Direct (4-connected) pixel offsets: up, down, left, right.
_STEP_U = wp.constant(wp.vec4i(-1, 1, 0, 0))
_STEP_V = wp.constant(wp.vec4i(0, 0, -1, 1))


@wp.func
def pixel_slot(first: int, thread: int, slots: int):
    """(pixel, candidate slot) of ``thread`` when each pixel from ``first`` on has
    ``slots`` threads: the layout of ``warptex.parallel.launch_ranges(per_item=slots)``."""
    return first + thread // slots, thread - (thread // slots) * slots


@wp.func
def strip_distance(
    a: wp.array2d(dtype=wp.int32), pa: int, b: wp.array2d(dtype=wp.int32), pb: int
) -> int:
    """Squared L2 distance between two pre-extracted N x 1 pixel strips (section 4.1)."""
    total = int(0)
    for t in range(a.shape[1]):
        d = a[pa, t] - b[pb, t]
        total += d * d
    return total


@wp.struct
class RoleStrips:
    """The N x 1 strips through every pixel of each role along its first and second pixel
    coordinate (section 4.1): ``own`` is role 0, ``next`` role 1, ``nnext`` role 2."""

    own_first: wp.array2d(dtype=wp.int32)
    own_second: wp.array2d(dtype=wp.int32)
    next_first: wp.array2d(dtype=wp.int32)
    next_second: wp.array2d(dtype=wp.int32)
    nnext_first: wp.array2d(dtype=wp.int32)
    nnext_second: wp.array2d(dtype=wp.int32)


@wp.func
def own_next_error(s: RoleStrips, p: int, q: int) -> int:
    """Crossbar pair (0, 1) of role-0 pixel ``p`` and role-1 pixel ``q``."""
    return strip_distance(s.own_second, p, s.next_first, q)


@wp.func
def next_nnext_error(s: RoleStrips, q: int, r: int) -> int:
    """Crossbar pair (1, 2) of role-1 pixel ``q`` and role-2 pixel ``r``."""
    return strip_distance(s.next_second, q, s.nnext_first, r)


@wp.func
def closing_error(s: RoleStrips, r: int, p: int) -> int:
    """Crossbar pair (2, 0) of role-2 pixel ``r`` and role-0 pixel ``p``."""
    return strip_distance(s.nnext_second, r, s.own_first, p)


@wp.func
def crossbar_error(s: RoleStrips, p: int, q: int, r: int) -> int:
    """Crossbar error of the triple of pixels (p, q, r) of roles 0, 1, 2 (section 4.1):
    how much its three slices disagree where they cross."""
    return own_next_error(s, p, q) + next_nnext_error(s, q, r) + closing_error(s, r, p)


@wp.kernel
def best_crossbar_triples(
    first: int,
    strips: RoleStrips,
    near1: wp.array2d(dtype=wp.int32),
    near2: wp.array2d(dtype=wp.int32),
    closing: wp.array2d(dtype=wp.int32),
    keys: wp.array2d(dtype=wp.int64),
    cand1: wp.array2d(dtype=wp.int32),
    cand2: wp.array2d(dtype=wp.int32),
    crossbar_errors: wp.array2d(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Score all S^2 triples of one pixel by crossbar error and keep the best, sorted.

    Section 4.1. ``near1``/``near2`` hold the S nearest strips found in roles 1 and 2.
    Pair (0, 1) of the crossbar error depends on the role-1 pixel alone and pair (2, 0) on
    the role-2 pixel alone, so each is computed once (the latter into this pixel's row of
    scratch ``closing``), and only pair (1, 2) for every triple. Ties are broken by the
    rank of the pair, so the order is fully reproducible. Pixel ``first + tid``.
    """
    p = first + wp.tid()
    s1 = near1.shape[1]
    s2 = near2.shape[1]
    keep = keys.shape[1]
    for j in range(s2):
        closing[p, j] = closing_error(strips, near2[p, j], p)
    n = int(0)
    for i in range(s1):
        q = near1[p, i]
        e01 = own_next_error(strips, p, q)
        for j in range(s2):
            r = near2[p, j]
            err = e01 + next_nnext_error(strips, q, r) + closing[p, j]
            key = wp.int64(err) * wp.int64(s1 * s2) + wp.int64(i * s2 + j)
            pos = int(-1)
            if n < keep:
                pos = n
                n += 1
            elif key < keys[p, keep - 1]:
                pos = keep - 1
            if pos >= 0:
                while pos > 0 and keys[p, pos - 1] > key:
                    keys[p, pos] = keys[p, pos - 1]
                    cand1[p, pos] = cand1[p, pos - 1]
                    cand2[p, pos] = cand2[p, pos - 1]
                    crossbar_errors[p, pos] = crossbar_errors[p, pos - 1]
                    pos -= 1
                keys[p, pos] = key
                cand1[p, pos] = q
                cand2[p, pos] = r
                crossbar_errors[p, pos] = err
    count[p] = n


@wp.kernel
def candidate_crossbar_errors(
    first: int,
    strips: RoleStrips,
    cand1: wp.array2d(dtype=wp.int32),
    cand2: wp.array2d(dtype=wp.int32),
    crossbar_errors: wp.array2d(dtype=wp.int32),
):
    """Crossbar error of stored candidate k of pixel p (section 4.1), recomputed; one
    thread per candidate slot of pixels ``first...``."""
    p, k = pixel_slot(first, wp.tid(), crossbar_errors.shape[1])
    crossbar_errors[p, k] = crossbar_error(strips, p, cand1[p, k], cand2[p, k])


@wp.struct
class CandidateCoords:
    """The candidates of every role-0 pixel as (u, v) pixel coordinates in the exemplar of
    one other role, and how many each pixel has (section 4.2)."""

    u: wp.array2d(dtype=wp.int32)
    v: wp.array2d(dtype=wp.int32)
    count: wp.array(dtype=wp.int32)


@wp.func
def mark_continuations(
    cand: CandidateCoords,
    p: int,
    own_height: int,
    own_width: int,
    height: int,
    width: int,
    marks: wp.array2d(dtype=wp.uint32),
    row: int,
    setting: bool,
):
    """Section 4.2: set (or, with ``setting`` false, clear) in bitmap row ``row`` the
    exemplar pixels that continue a candidate of a direct neighbour of p: the direct
    (4-connected, toroidal) neighbours of its coordinates. Clearing zeroes whole words, as
    every bit set in the row was set here."""
    uv = pixel_coords(p, own_width)
    for d in range(4):
        q = pixel_index(uv[0] + _STEP_U[d], uv[1] + _STEP_V[d], own_height, own_width)
        for j in range(cand.count[q]):
            for e in range(4):
                du = _STEP_U[e]
                dv = _STEP_V[e]
                # Along a side of one pixel a neighbour would be the pixel itself.
                if (du != 0 and height > 1) or (dv != 0 and width > 1):
                    at = pixel_index(cand.u[q, j] + du, cand.v[q, j] + dv, height, width)
                    word = at >> 5
                    if setting:
                        marks[row, word] = marks[row, word] | bit_mask(at)
                    else:
                        marks[row, word] = wp.uint32(0)


@wp.func
def keep_marked(
    cand: CandidateCoords,
    p: int,
    width: int,
    marks: wp.array2d(dtype=wp.uint32),
    row: int,
    keep: wp.array2d(dtype=wp.int32),
    i: int,
):
    """Clear the flag of each candidate of p whose coordinates are not marked."""
    for k in range(cand.count[p]):
        at = cand.u[p, k] * width + cand.v[p, k]
        if (marks[row, at >> 5] & bit_mask(at)) == wp.uint32(0):
            keep[i, k] = 0


@wp.func
def keep_continued(
    cand: CandidateCoords,
    p: int,
    height: wp.vec3i,
    width: wp.vec3i,
    role: int,
    marks: wp.array2d(dtype=wp.uint32),
    row: int,
    keep: wp.array2d(dtype=wp.int32),
    i: int,
):
    """Section 4.2 in the exemplar of ``role``: clear the flag of each candidate of p whose
    coordinates there continue no candidate of a direct neighbour, through bitmap row
    ``row``, left zeroed again for the next role."""
    h0 = height[0]
    w0 = width[0]
    mark_continuations(cand, p, h0, w0, height[role], width[role], marks, row, True)
    keep_marked(cand, p, width[role], marks, row, keep, i)
    mark_continuations(cand, p, h0, w0, height[role], width[role], marks, row, False)


@wp.kernel
def coherent_candidates(
    first: int,
    batch_first: int,
    pixels: wp.array(dtype=wp.int32),
    cand1: CandidateCoords,
    cand2: CandidateCoords,
    height: wp.vec3i,
    width: wp.vec3i,
    marks: wp.array2d(dtype=wp.uint32),
    keep: wp.array2d(dtype=wp.int32),
):
    """Flag the candidates forming coherent patches in all three exemplars (section 4.2):
    a candidate is kept when, in both other exemplars, its coordinates continue a
    candidate of one of its pixel's direct neighbours.

    Candidate coordinates come unpacked as (u, v) pixel coordinates of roles 1 and 2. One
    thread per listed pixel ``pixels[i]``, i from ``first`` on, whose candidates are flagged
    in row i of ``keep``; it marks the continued pixels of each role in row
    ``i - batch_first`` of the zeroed bitmaps ``marks`` (one bit per pixel of the larger
    exemplar) and leaves that row zeroed again.
    """
    i = first + wp.tid()
    p = pixels[i]
    row = i - batch_first
    for k in range(keep.shape[1]):
        keep[i, k] = wp.where(k < cand1.count[p], 1, 0)
    keep_continued(cand1, p, height, width, 1, marks, row, keep, i)
    keep_continued(cand2, p, height, width, 2, marks, row, keep, i)
