"""Kernels finding the voxels that a triangle mesh's surface passes through.

Dong 2008, section 6.2: only a thin layer of voxels around a surface is synthesized.
A voxel v is the unit cube [v, v+1)^3 of the finest level; a triangle touches it when the
separating-axis test (Akenine-Moeller 2001) finds no axis separating them.
"""

import warp as wp

from kernels.common import floor_voxel

# No fused multiply-adds (CUDA's default, which fuses more than the CPU build): the shell's voxels
# must come out the same on every device.
wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.func
def separated_on(axis: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, half: float) -> bool:
    """Do the triangle (relative to the box centre) and the box project apart on ``axis``?"""
    pa = wp.dot(a, axis)
    pb = wp.dot(b, axis)
    pc = wp.dot(c, axis)
    r = half * (wp.abs(axis[0]) + wp.abs(axis[1]) + wp.abs(axis[2]))
    return wp.min(pa, wp.min(pb, pc)) > r or wp.max(pa, wp.max(pb, pc)) < -r


@wp.func
def triangle_touches_voxel(a: wp.vec3, b: wp.vec3, c: wp.vec3, voxel: wp.vec3i) -> bool:
    """Separating-axis test of a triangle against the unit cube of ``voxel``."""
    centre = wp.vec3(float(voxel[0]) + 0.5, float(voxel[1]) + 0.5, float(voxel[2]) + 0.5)
    a = a - centre
    b = b - centre
    c = c - centre
    half = 0.5
    edges = wp.matrix_from_rows(b - a, c - b, a - c)
    for i in range(3):
        for j in range(3):
            unit = wp.vec3(0.0, 0.0, 0.0)
            unit[j] = 1.0
            if separated_on(wp.cross(unit, edges[i]), a, b, c, half):
                return False
    for j in range(3):
        unit = wp.vec3(0.0, 0.0, 0.0)
        unit[j] = 1.0
        if separated_on(unit, a, b, c, half):
            return False
    return not separated_on(wp.cross(b - a, c - a), a, b, c, half)


@wp.kernel
def touched_voxels(
    first: int,
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    offsets: wp.array(dtype=wp.int32),
    write: int,
    counts: wp.array(dtype=wp.int32),
    voxels: wp.array(dtype=wp.vec3i),
):
    """Count the voxels each triangle touches (``write`` = 0), or write them from the
    triangle's offset on (``write`` = 1), visiting them in the same order both times.
    Triangle ``first + tid``."""
    f = first + wp.tid()
    a = vertices[faces[f][0]]
    b = vertices[faces[f][1]]
    c = vertices[faces[f][2]]
    lo = floor_voxel(wp.min(a, wp.min(b, c)))
    hi = floor_voxel(wp.max(a, wp.max(b, c)))
    n = int(0)
    if write == 1:
        n = offsets[f]
    for x in range(lo[0], hi[0] + 1):
        for y in range(lo[1], hi[1] + 1):
            for z in range(lo[2], hi[2] + 1):
                v = wp.vec3i(x, y, z)
                if triangle_touches_voxel(a, b, c, v):
                    if write == 1:
                        voxels[n] = v
                    n += 1
    if write == 0:
        counts[f] = n
