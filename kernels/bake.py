"""Kernels that find, for every texel of a UV texture, the surface point it shows: the
points whose solid-texture colours bake a mesh's texture (Dong 2008, section 6.2).

Texel (x, y) of a W x H image has its centre at UV ((x + 0.5) / W, 1 - (y + 0.5) / H):
image rows run down while V runs up. A texel belongs to the lowest-numbered triangle
whose UV image covers its centre, so overlapping charts resolve the same way everywhere.
"""

import warp as wp

# No fused multiply-adds (CUDA's default, which fuses more than the CPU build): texel
# owners and surface points must come out the same on every device.
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

NO_TRIANGLE = wp.constant(2147483647)


@wp.func
def texel_uv(x: int, y: int, width: int, height: int) -> wp.vec2:
    """UV of the centre of texel ``(x, y)`` (rows run down, V up)."""
    return wp.vec2((float(x) + 0.5) / float(width), 1.0 - (float(y) + 0.5) / float(height))


@wp.func
def barycentric(p: wp.vec2, a: wp.vec2, b: wp.vec2, c: wp.vec2) -> wp.vec3:
    """Barycentric coordinates of p in triangle abc; a component < 0 means outside."""
    d = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
    if d == 0.0:
        return wp.vec3(-1.0, -1.0, -1.0)
    wa = ((b[1] - c[1]) * (p[0] - c[0]) + (c[0] - b[0]) * (p[1] - c[1])) / d
    wb = ((c[1] - a[1]) * (p[0] - c[0]) + (a[0] - c[0]) * (p[1] - c[1])) / d
    return wp.vec3(wa, wb, 1.0 - wa - wb)


@wp.func
def covers(w: wp.vec3) -> bool:
    """Whether barycentric coordinates ``w`` lie in their triangle, edges included."""
    return w[0] >= 0.0 and w[1] >= 0.0 and w[2] >= 0.0


@wp.kernel
def claim_texels(
    uv: wp.array(dtype=wp.vec2),
    faces: wp.array(dtype=wp.vec3i),
    width: int,
    height: int,
    owner: wp.array(dtype=wp.int32),
):
    """Each triangle claims the texels whose centres its UV image covers (lowest wins)."""
    f = wp.tid()
    a = uv[faces[f][0]]
    b = uv[faces[f][1]]
    c = uv[faces[f][2]]
    # Clamped to just beyond [0, 1] before int(): a float beyond int32 has no int (C leaves
    # it undefined; a CPU gave INT_MIN, and such a triangle claimed no texel).
    lo = wp.max(wp.min(a, wp.min(b, c)), wp.vec2(-1.0, -1.0))
    hi = wp.min(wp.max(a, wp.max(b, c)), wp.vec2(2.0, 2.0))
    x0 = wp.max(int(wp.floor(lo[0] * float(width))) - 1, 0)
    x1 = wp.min(int(wp.floor(hi[0] * float(width))) + 1, width - 1)
    y0 = wp.max(int(wp.floor((1.0 - hi[1]) * float(height))) - 1, 0)
    y1 = wp.min(int(wp.floor((1.0 - lo[1]) * float(height))) + 1, height - 1)
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            if covers(barycentric(texel_uv(x, y, width, height), a, b, c)):
                wp.atomic_min(owner, y * width + x, f)


@wp.kernel
def texel_points(
    uv: wp.array(dtype=wp.vec2),
    positions: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    owner: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    points: wp.array(dtype=wp.vec3d),
):
    """The surface point of each claimed texel, interpolated in its owning triangle.

    In float64 like the positions, and from the triangle's first corner: weights summing to
    one only within float32 rounding would otherwise move points far from the origin (by
    a tenth of a voxel 10^6 voxels out), away from the point whose color a query gets.
    """
    t = wp.tid()
    f = owner[t]
    if f == NO_TRIANGLE:
        return
    face = faces[f]
    w = wp.vec3d(barycentric(texel_uv(t % width, t // width, width, height), uv[face[0]],
                             uv[face[1]], uv[face[2]]))
    a = positions[face[0]]
    points[t] = a + w[1] * (positions[face[1]] - a) + w[2] * (positions[face[2]] - a)
