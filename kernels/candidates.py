"""Kernels of the 3D candidate pre-computation (Dong 2008, section 4).

Exemplar roles are cyclic: role 0 is the exemplar whose pixels own the candidate lists,
role 1 the next axis and role 2 the one after. An exemplar of role k spans the volume axes
(k+1, k+2) as its (first, second) coordinates, so role k and role k+1 share the volume
axis k+2: the second-coordinate strip of role k meets the first-coordinate strip of
role k+1. The three crossbar pairs are therefore (0, 1), (1, 2) and (2, 0).
"""

import warp as wp

from kernels.common import pixel_index

wp.set_module_options({"enable_backward": False})


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


@wp.func
def crossbar_rest(
    next_second: wp.array2d(dtype=wp.int32),
    nnext_first: wp.array2d(dtype=wp.int32),
    nnext_second: wp.array2d(dtype=wp.int32),
    own_first: wp.array2d(dtype=wp.int32),
    p: int,
    q: int,
    r: int,
) -> int:
    """The crossbar pairs (1, 2) and (2, 0) of triple (p, q, r); pair (0, 1) depends on
    (p, q) alone, so the search computes it once per q."""
    return strip_distance(next_second, q, nnext_first, r) + strip_distance(
        nnext_second, r, own_first, p
    )


@wp.kernel
def best_crossbar_triples(
    first: int,
    own_first: wp.array2d(dtype=wp.int32),
    own_second: wp.array2d(dtype=wp.int32),
    next_first: wp.array2d(dtype=wp.int32),
    next_second: wp.array2d(dtype=wp.int32),
    nnext_first: wp.array2d(dtype=wp.int32),
    nnext_second: wp.array2d(dtype=wp.int32),
    near1: wp.array2d(dtype=wp.int32),
    near2: wp.array2d(dtype=wp.int32),
    keys: wp.array2d(dtype=wp.int64),
    cand1: wp.array2d(dtype=wp.int32),
    cand2: wp.array2d(dtype=wp.int32),
    cb: wp.array2d(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Score all S^2 triples of one pixel by crossbar error and keep the best, sorted.

    Section 4.1. ``*_first``/``*_second`` are the strips of each role along its first and
    second pixel coordinate; ``near1``/``near2`` the S nearest strips found in roles 1
    and 2. The crossbar pairs are (0, 1), (1, 2) and (2, 0): the second-coordinate strip
    of a role meets the first-coordinate strip of the next. Ties are broken by the rank
    of the pair, so the order is fully reproducible. Pixel ``first + tid``.
    """
    p = first + wp.tid()
    s1 = near1.shape[1]
    s2 = near2.shape[1]
    keep = keys.shape[1]
    n = int(0)
    for i in range(s1):
        q = near1[p, i]
        e01 = strip_distance(own_second, p, next_first, q)
        for j in range(s2):
            r = near2[p, j]
            err = e01 + crossbar_rest(next_second, nnext_first, nnext_second, own_first, p, q, r)
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
                    cb[p, pos] = cb[p, pos - 1]
                    pos -= 1
                keys[p, pos] = key
                cand1[p, pos] = q
                cand2[p, pos] = r
                cb[p, pos] = err
    count[p] = n


@wp.kernel
def candidate_crossbar_errors(
    first: int,
    own_first: wp.array2d(dtype=wp.int32),
    own_second: wp.array2d(dtype=wp.int32),
    next_first: wp.array2d(dtype=wp.int32),
    next_second: wp.array2d(dtype=wp.int32),
    nnext_first: wp.array2d(dtype=wp.int32),
    nnext_second: wp.array2d(dtype=wp.int32),
    cand1: wp.array2d(dtype=wp.int32),
    cand2: wp.array2d(dtype=wp.int32),
    cb: wp.array2d(dtype=wp.int32),
):
    """Crossbar error of stored candidate k of pixel p (section 4.1), recomputed; one
    thread per candidate slot of pixels ``first...``."""
    p, k = pixel_slot(first, wp.tid(), cb.shape[1])
    q = cand1[p, k]
    r = cand2[p, k]
    err = strip_distance(own_second, p, next_first, q)
    cb[p, k] = err + crossbar_rest(next_second, nnext_first, nnext_second, own_first, p, q, r)


@wp.func
def is_adjacent(du: int, dv: int, height: int, width: int) -> bool:
    """True when a pixel offset (du, dv) joins direct (4-connected, toroidal) neighbours."""
    du = wp.abs(du)
    dv = wp.abs(dv)
    return wp.min(du, height - du) + wp.min(dv, width - dv) == 1


@wp.func
def has_continuous_neighbor(
    cand_u: wp.array2d(dtype=wp.int32),
    cand_v: wp.array2d(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    p: int,
    k: int,
    own_height: int,
    own_width: int,
    height: int,
    width: int,
) -> bool:
    """Section 4.2: a candidate of a direct neighbour of p continues candidate k of p."""
    u = p // own_width
    v = p - u * own_width
    cu = cand_u[p, k]
    cv = cand_v[p, k]
    for d in range(4):
        du = int(0)
        dv = int(0)
        if d == 0:
            du = -1
        elif d == 1:
            du = 1
        elif d == 2:
            dv = -1
        else:
            dv = 1
        q = pixel_index(u + du, v + dv, own_height, own_width)
        for j in range(count[q]):
            if is_adjacent(cand_u[q, j] - cu, cand_v[q, j] - cv, height, width):
                return True
    return False


@wp.kernel
def coherent_candidates(
    first: int,
    pixels: wp.array(dtype=wp.int32),
    cand1_u: wp.array2d(dtype=wp.int32),
    cand1_v: wp.array2d(dtype=wp.int32),
    cand2_u: wp.array2d(dtype=wp.int32),
    cand2_v: wp.array2d(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    height: wp.vec3i,
    width: wp.vec3i,
    keep: wp.array2d(dtype=wp.int32),
):
    """Flag the candidates forming coherent patches in all three exemplars (section 4.2).

    Candidate coordinates come unpacked as (u, v) pixel coordinates of roles 1 and 2. One
    thread per candidate slot of the listed ``pixels`` from ``first`` on; row i of ``keep``
    is ``pixels[i]``.
    """
    i, k = pixel_slot(first, wp.tid(), keep.shape[1])
    p = pixels[i]
    flag = int(0)
    if k < count[p]:
        h0 = height[0]
        w0 = width[0]
        if has_continuous_neighbor(
            cand1_u, cand1_v, count, p, k, h0, w0, height[1], width[1]
        ) and has_continuous_neighbor(cand2_u, cand2_v, count, p, k, h0, w0, height[2], width[2]):
            flag = 1
    keep[i, k] = flag
