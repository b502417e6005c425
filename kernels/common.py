"""Integer building blocks shared by every warptex kernel.

Everything here is integer arithmetic so that a kernel gives bit-identical results on the
CPU and on CUDA: exemplar features are quantized to ints and distances are exact sums.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

# Tells warptex's kernels from another package named ``kernels`` (warptex/__init__.py).
WARPTEX_KERNELS = True

# Integer coordinates (of voxels, blocks or bricks) packed into one int64 key: 21 bits per
# axis, x most significant, each biased to be non-negative. warptex.keysets packs on the host.
KEY_BIAS = 1 << 20
KEY_BITS = 21


@wp.func
def wrap(x: int, n: int) -> int:
    """``x`` modulo ``n`` in ``[0, n)``; exemplars are toroidal."""
    r = x % n
    if r < 0:
        r += n
    return r


@wp.func
def floor_div(x: int, n: int) -> int:
    """``x // n`` rounded toward minus infinity for ``n > 0``, whatever the Warp version:
    Warp's integer ``//`` truncated toward zero before NVIDIA/warp#1918 was fixed, which
    would move every lattice cell of the jitter at negative coordinates."""
    if x >= 0:
        return x // n
    return -((n - 1 - x) // n)


@wp.func
def pixel_index(u: int, v: int, height: int, width: int) -> int:
    """Row-major index of exemplar pixel ``(u, v)`` after toroidal wrapping."""
    return wrap(u, height) * width + wrap(v, width)


@wp.func
def pixel_coords(pixel: int, width: int) -> wp.vec2i:
    """Coordinates ``(u, v)`` of row-major exemplar pixel index ``pixel``: the inverse of
    :func:`pixel_index` (a remainder by product, as Warp's ``%`` rounds like C's)."""
    u = pixel // width
    return wp.vec2i(u, pixel - u * width)


@wp.func
def bit_mask(bit: int) -> wp.uint32:
    """The mask of bit ``bit`` in its uint32 word: bitmaps keep bit i in word ``i >> 5``."""
    return wp.uint32(1) << wp.uint32(bit & 31)


_MIX1 = wp.constant(wp.uint32(0x7FEB352D))
_MIX2 = wp.constant(wp.uint32(0x846CA68B))
_GOLDEN = wp.constant(wp.uint32(0x9E3779B9))


@wp.func
def hash_u32(x: wp.uint32) -> wp.uint32:
    """A well-mixed 32-bit integer hash (lowbias32), the source of all randomness."""
    x ^= x >> wp.uint32(16)
    x *= _MIX1
    x ^= x >> wp.uint32(15)
    x *= _MIX2
    x ^= x >> wp.uint32(16)
    return x


@wp.func
def hash_cell(cx: int, cy: int, cz: int, seed: int, salt: int) -> wp.uint32:
    """Hash of an integer lattice cell, a seed and a salt; defined over all of Z^3."""
    h = hash_u32(wp.uint32(seed) ^ _GOLDEN)
    h = hash_u32(h ^ wp.uint32(cx))
    h = hash_u32(h ^ wp.uint32(cy))
    h = hash_u32(h ^ wp.uint32(cz))
    return hash_u32(h ^ wp.uint32(salt))


@wp.func
def floor_voxel(p: Any) -> wp.vec3i:
    """The voxel (unit cube ``[v, v + 1)^3``) holding point ``p`` (float32 or float64)."""
    return wp.vec3i(int(wp.floor(p[0])), int(wp.floor(p[1])), int(wp.floor(p[2])))


@wp.func
def cell_local_index(p: wp.vec3i, shift: int) -> int:
    """Flat index of voxel ``p`` in its cell of ``2^shift`` voxels a side, x slowest: the
    low ``shift`` bits of each coordinate (``warptex.keysets.local_index`` on the device).
    Shifts and masks, as ``%`` rounds negative coordinates towards zero."""
    low = (1 << shift) - 1
    return ((((p[0] & low) << shift) + (p[1] & low)) << shift) + (p[2] & low)


@wp.func
def plane_offset(axis: int, a: int, b: int) -> wp.vec3i:
    """Volume offset of pixel offset (a, b) in the plane of the exemplar of ``axis``: the
    exemplar of axis k spans volume axes (k+1, k+2) as its (first, second) coordinates."""
    d = wp.vec3i(0, 0, 0)
    d[(axis + 1) % 3] = a
    d[(axis + 2) % 3] = b
    return d
