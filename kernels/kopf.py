"""Kernels of solid texture optimization (Kopf et al. 2007, sections 4 and 5).

The solid ``s`` is a periodic ``n^3`` volume stored as ``(n^3, F)`` floats, voxel ``(x, y, z)``
at row ``(x * n + y) * n + z``. The neighbourhood ``s_v,i`` of voxel ``v`` is the 8x8 window
of the slice perpendicular to axis ``i`` with rows along axis ``i+1`` and columns along axis
``i+2`` (the orientation of the exemplar of axis ``i``), offsets ``-4..3`` around ``v``.
The search runs on the sparser grid ``g_i`` (section 4.2, m = 2): voxels whose two in-plane
coordinates are even. Centre ``c`` of ``g_i`` is the voxel with coordinate ``c0`` along
axis ``i`` and ``2*c1``, ``2*c2`` along axes ``i+1``, ``i+2`` for ``c = (c0*h + c1)*h + c2``
and ``h = n/2``.

Exemplars of the three axes are concatenated into one ``(sum h*w, F)`` array with per-axis
row offsets; a match is the index of its window's centre pixel inside its axis' exemplar.
"""

import warp as wp

from kernels.common import pixel_coords, pixel_index, plane_offset, wrap

wp.set_module_options({"enable_backward": False})

WINDOW = 8  # 8x8 neighbourhoods (section 5)
HALF = 4  # window offsets run -HALF .. WINDOW-HALF-1
MEAN_SHIFT_STEPS = 2  # after the densest texel, before the final average of its cluster
MAX_COEFFS = 96
"""Most PCA coefficients kept: 95% of the variance of the bundled exemplars' 8x8 RGB windows
needs 30 to 71 (bricks_red's coarse levels), 94 with a feature-distance channel; fewer
kept is warned of."""

projection = wp.types.vector(length=MAX_COEFFS, dtype=wp.float32)
"""A PCA-projected neighbourhood; unused trailing coefficients stay zero."""


@wp.func
def voxel_index(p: wp.vec3i, n: int) -> int:
    """Row of voxel ``p`` of the periodic solid (toroidal wrapping)."""
    return (wrap(p[0], n) * n + wrap(p[1], n)) * n + wrap(p[2], n)


@wp.func
def window_voxel(p: wp.vec3i, axis: int, a: int, b: int, n: int) -> int:
    """Row of entry ``(a, b)`` of the 8x8 window of voxel ``p`` in its slice across
    ``axis`` (section 3's ``s_v,i``)."""
    return voxel_index(p + plane_offset(axis, a - HALF, b - HALF), n)


@wp.func
def window_texel(centre: wp.vec2i, a: int, b: int, height: int, width: int) -> int:
    """Pixel of entry ``(a, b)`` of the exemplar window centred on pixel ``centre``
    (its row and column), wrapping around the exemplar."""
    return pixel_index(centre[0] + a - HALF, centre[1] + b - HALF, height, width)


@wp.func
def voxel_at(row: int, n: int) -> wp.vec3i:
    """Voxel of ``row`` of an ``n^3`` solid, x slowest: the inverse of :func:`voxel_index`."""
    return wp.vec3i(row // (n * n), (row // n) % n, row % n)


@wp.func
def grid_centre(axis: int, c: int, n: int) -> wp.vec3i:
    """Voxel of centre ``c`` of the sparser search grid ``g_axis`` (section 4.2)."""
    h = n // 2
    c2 = c % h
    c1 = (c // h) % h
    p = wp.vec3i(0, 0, 0)
    p[axis] = c // (h * h)
    p[(axis + 1) % 3] = 2 * c1
    p[(axis + 2) % 3] = 2 * c2
    return p


@wp.func
def grid_index(axis: int, p: wp.vec3i, n: int) -> int:
    """Index in ``g_axis`` of voxel ``p``, whose in-plane coordinates are even."""
    h = n // 2
    c1 = wrap(p[(axis + 1) % 3], n) // 2
    c2 = wrap(p[(axis + 2) % 3], n) // 2
    return (wrap(p[axis], n) * h + c1) * h + c2


@wp.func
def window_distance(
    s: wp.array2d(dtype=wp.float32),
    n: int,
    axis: int,
    p: wp.vec3i,
    ex: wp.array2d(dtype=wp.float32),
    ex_first: int,
    height: int,
    width: int,
    centre: int,
) -> float:
    """L2 distance ``|s_v,i - e_v,i|`` between the window of ``p`` and the exemplar window
    centred on pixel ``centre`` (equation 1)."""
    uv = pixel_coords(centre, width)
    total = float(0.0)
    for a in range(WINDOW):
        for b in range(WINDOW):
            q = window_voxel(p, axis, a, b, n)
            e = ex_first + window_texel(uv, a, b, height, width)
            for f in range(s.shape[1]):
                d = s[q, f] - ex[e, f]
                total += d * d
    return wp.sqrt(total)


@wp.kernel
def project_windows(
    first: int,
    s: wp.array2d(dtype=wp.float32),
    n: int,
    axis: int,
    mean: wp.array(dtype=wp.float32),
    basis: wp.array(dtype=projection),
    coeffs: wp.array(dtype=projection),
):
    """PCA coefficients of ``s_v,i`` for the centres of ``g_axis`` (section 4.2).

    ``mean`` and ``basis`` have one row per window entry ``(a * 8 + b) * F + f``.
    """
    c = wp.tid() + first
    p = grid_centre(axis, c, n)
    acc = projection()
    nfeat = s.shape[1]
    for a in range(WINDOW):
        for b in range(WINDOW):
            q = window_voxel(p, axis, a, b, n)
            for f in range(nfeat):
                k = (a * WINDOW + b) * nfeat + f
                acc += basis[k] * (s[q, f] - mean[k])
    coeffs[c] = acc


@wp.kernel
def keep_better_match(
    first: int,
    s: wp.array2d(dtype=wp.float32),
    n: int,
    axis: int,
    ex: wp.array2d(dtype=wp.float32),
    ex_first: int,
    height: int,
    width: int,
    found: wp.array(dtype=wp.int32),
    r: float,
    min_distance: float,
    match: wp.array(dtype=wp.int32),
    weight: wp.array(dtype=wp.float32),
    energy: wp.array(dtype=wp.float32),
):
    """Settle the search for each centre of ``g_axis`` and prepare its IRLS weight.

    The ANN search returns a window within (1 + eps) of the nearest, so it can be worse than
    the current match ``match[c]`` (-1 when none); the better of the two is kept, which makes
    the search phase never raise the energy. ``energy`` receives ``|s_v,i - e_v,i|^r``
    (equation 1), ``weight`` the IRLS weight ``|s_v,i - e_v,i|^(r-2)`` (equation 2), with the
    distance floored at ``min_distance`` so exact matches do not get infinite weight.
    """
    c = wp.tid() + first
    p = grid_centre(axis, c, n)
    best = found[c]
    dist = window_distance(s, n, axis, p, ex, ex_first, height, width, best)
    current = match[c]
    if current >= 0 and current != best:
        kept = window_distance(s, n, axis, p, ex, ex_first, height, width, current)
        if kept <= dist:
            best = current
            dist = kept
    match[c] = best
    energy[c] = wp.pow(dist, r)
    weight[c] = wp.pow(wp.max(dist, min_distance), r - 2.0)


MAX_TEXELS = 48
"""Texels a voxel receives: 16 windows of the m = 2 grid cover it in each of three slices."""
MAX_FEATURES = 8  # channels mean-shift clustering handles

texel_list = wp.types.vector(length=MAX_TEXELS, dtype=wp.int32)
weight_list = wp.types.vector(length=MAX_TEXELS, dtype=wp.float32)
feature_point = wp.types.vector(length=MAX_FEATURES, dtype=wp.float32)


@wp.func
def texel_point(ex: wp.array2d(dtype=wp.float32), e: int) -> feature_point:
    """Exemplar texel ``e`` as a point of the mean-shift feature space."""
    point = feature_point()
    for f in range(ex.shape[1]):
        point[f] = ex[e, f]
    return point


@wp.func
def texel_gap(ex: wp.array2d(dtype=wp.float32), e: int, point: feature_point) -> float:
    """Squared distance between exemplar texel ``e`` and ``point``."""
    total = float(0.0)
    for f in range(ex.shape[1]):
        d = ex[e, f] - point[f]
        total += d * d
    return total


@wp.func
def densest_texel(ex: wp.array2d(dtype=wp.float32), texels: texel_list, weights: weight_list,
                  count: int, h2: float) -> int:
    """The texel with the most weight within the bandwidth (``h2`` its square): where the
    mean shift of the dominant cluster starts (section 4.1). The first of equals wins."""
    density = weights
    for i in range(count):
        point = texel_point(ex, texels[i])
        for j in range(i + 1, count):
            if texel_gap(ex, texels[j], point) <= h2:
                density[i] = density[i] + weights[j]
                density[j] = density[j] + weights[i]
    best = int(0)
    for i in range(1, count):
        if density[i] > density[best]:
            best = i
    return best


@wp.func
def cluster_mean(ex: wp.array2d(dtype=wp.float32), texels: texel_list, weights: weight_list,
                 count: int, centre: feature_point, h2: float) -> feature_point:
    """Weighted mean of the texels within the bandwidth of ``centre`` (``h2`` its square):
    one step of mean shift with a flat kernel; with ``h2`` below zero, of every texel, the
    plain average of equation 4. ``centre`` itself where no texel is that close."""
    nfeat = ex.shape[1]
    acc = feature_point()
    total = float(0.0)
    for i in range(count):
        e = texels[i]
        near = h2 < 0.0
        if not near:  # Warp evaluates both sides of `or`: no distances for plain averages
            near = texel_gap(ex, e, centre) <= h2
        if near:
            total += weights[i]
            for f in range(nfeat):
                acc[f] = acc[f] + weights[i] * ex[e, f]
    if total <= 0.0:
        return centre
    return acc / total


@wp.kernel
def optimize_voxels(
    first: int,
    order: wp.array(dtype=wp.int32),
    n: int,
    constrained: wp.vec3i,
    ex: wp.array2d(dtype=wp.float32),
    ex_first: wp.vec3i,
    height: wp.vec3i,
    width: wp.vec3i,
    grid_first: wp.vec3i,
    match: wp.array(dtype=wp.int32),
    weight: wp.array(dtype=wp.float32),
    penalty: wp.array(dtype=wp.float32),
    bandwidth: float,
    s: wp.array2d(dtype=wp.float32),
):
    """Optimization phase (section 4.1, equation 4) for voxels ``order[first + tid]``.

    The new ``s_v`` is the weighted average of the texels ``e_u,i,v`` that the matched windows
    of all grid centres ``u`` whose window covers ``v`` put on ``v``. Each weight ``w_u,i`` is
    divided by ``1 + penalty`` of its texel, the histogram term of equation 5 (zero without
    histogram matching). With a ``bandwidth`` above zero only the texels of the dominant
    mean-shift cluster are averaged (section 4.1, after Wexler et al. 2007). ``s`` is not
    read: the texels come from the exemplar, so updating in place is safe.
    """
    v = order[wp.tid() + first]
    p = voxel_at(v, n)
    texels = texel_list()
    weights = weight_list()
    count = int(0)
    for axis in range(3):
        if constrained[axis] != 0:
            row = p[(axis + 1) % 3]
            col = p[(axis + 2) % 3]
            for a in range(WINDOW):
                # Only windows centred on the grid g_axis exist: both centre coordinates even.
                if ((row - (a - HALF)) & 1) == 0:
                    for b in range(WINDOW):
                        if ((col - (b - HALF)) & 1) == 0:
                            centre = p - plane_offset(axis, a - HALF, b - HALF)
                            g = grid_first[axis] + grid_index(axis, centre, n)
                            uv = pixel_coords(match[g], width[axis])
                            e = ex_first[axis] + window_texel(uv, a, b, height[axis],
                                                              width[axis])
                            texels[count] = e
                            weights[count] = weight[g] / (1.0 + penalty[e])
                            count += 1
    h2 = float(-1.0)
    mode = feature_point()
    if bandwidth > 0.0:
        h2 = bandwidth * bandwidth
        mode = texel_point(ex, texels[densest_texel(ex, texels, weights, count, h2)])
        for _step in range(MEAN_SHIFT_STEPS):
            mode = cluster_mean(ex, texels, weights, count, mode, h2)
    mode = cluster_mean(ex, texels, weights, count, mode, h2)
    for f in range(ex.shape[1]):
        s[v, f] = mode[f]


@wp.func
def linear_tap(i: int, t: int, n: int) -> wp.vec2i:
    """Coarse voxel below fine voxel ``i`` along one axis and which of the two taps ``t``."""
    base = (i - 1) >> 1  # coarse centre (i + 0.5) / 2 - 0.5 lies in [base, base + 1)
    return wp.vec2i(wrap(base + t, n), (i & 1) * 2 + t)


@wp.kernel
def upsample_trilinear(
    coarse: wp.array2d(dtype=wp.float32),
    n: int,
    fine: wp.array2d(dtype=wp.float32),
):
    """Trilinear interpolation of the periodic ``n^3`` solid onto the ``(2n)^3`` solid
    (section 4, switching to a finer level)."""
    i = wp.tid()
    p = voxel_at(i, 2 * n)
    # Fine voxel i sits at coarse coordinate i/2 - 1/4: even voxels weigh their lower coarse
    # neighbour 1/4 and upper 3/4, odd voxels the other way round; index = parity*2 + tap.
    taps = wp.vec4(0.25, 0.75, 0.75, 0.25)
    for f in range(fine.shape[1]):
        fine[i, f] = 0.0
    for tx in range(2):
        ax = linear_tap(p[0], tx, n)
        for ty in range(2):
            ay = linear_tap(p[1], ty, n)
            for tz in range(2):
                az = linear_tap(p[2], tz, n)
                w = taps[ax[1]] * taps[ay[1]] * taps[az[1]]
                q = voxel_index(wp.vec3i(ax[0], ay[0], az[0]), n)
                for f in range(fine.shape[1]):
                    fine[i, f] = fine[i, f] + w * coarse[q, f]
