"""Kernels of point queries on the sparse brick store (Dong 2008, sections 5.2 and 6.2).

Finest-level results live in bricks of 8^3 voxels found through an open-addressing hash
table keyed by packed brick coordinates. A brick may be partly filled: one bit per voxel
says whether it is stored, and only stored voxels take room in the pool, packed in brick
order (the TileTree of section 6.2 likewise stores only voxels near the surface). A voxel
is stored as its triple of exemplar pixel
indices, as the paper's GPU implementation keeps "three 2-channel 16 bit" triples
(section 6.2), and its color is the average of the three exemplar colors (section 5.1).

Texture space: one unit is one finest voxel; voxel v occupies [v, v + 1)^3, its center is
v + 0.5. ``nearest`` reads voxel floor(p); ``trilinear`` blends the 8 voxels around p - 0.5.
"""

from typing import Any

import warp as wp

from kernels.common import KEY_BIAS, KEY_BITS, bit_mask, cell_local_index, floor_voxel

# No fused multiply-adds (CUDA's default): the plugin's traced lookups (Dr.Jit) repeat
# the trilinear blend with separate roundings and must match to the bit.
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

BRICK_SHIFT = 3  # bricks are 2^BRICK_SHIFT voxels wide
BRICK = 1 << BRICK_SHIFT
BRICK_VOXELS = BRICK**3
VALID_WORDS = BRICK_VOXELS // 32  # 32-bit words of a brick's stored-voxel bits
MAX_CHANNELS = 4  # gray, RGB or RGBA exemplars
EMPTY = wp.constant(wp.int64(-1))

_SHIFT = wp.constant(BRICK_SHIFT)
_BIAS = wp.constant(wp.int64(KEY_BIAS))
_SHIFT_Y = wp.constant(wp.int64(KEY_BITS))
_SHIFT_X = wp.constant(wp.int64(2 * KEY_BITS))
_MIX1 = wp.constant(wp.uint64(0xBF58476D1CE4E5B9))
_MIX2 = wp.constant(wp.uint64(0x94D049BB133111EB))


@wp.struct
class BrickIndex:
    """The hash table (``keys`` -> brick ``slots``) and each brick slot's voxels and last use."""

    keys: wp.array(dtype=wp.int64)  # EMPTY where free; capacity is a power of two
    slots: wp.array(dtype=wp.int32)
    mask: wp.int64  # capacity - 1
    stamps: wp.array(dtype=wp.int64)  # per slot, for least-recently-used eviction
    valid: wp.array(dtype=wp.uint32)  # per slot, VALID_WORDS words of stored-voxel bits
    base: wp.array(dtype=wp.int32)  # per slot, pool position of the brick's first voxel
    partial: int  # 0 when every stored brick is whole, so the bits need no reading
    reach: wp.float64  # points lie strictly within +-reach, where brick keys do not wrap


@wp.func
def brick_key(voxel: wp.vec3i) -> wp.int64:
    """Packed coordinates of the brick holding ``voxel`` (21 bits per axis, biased)."""
    bx = wp.int64(voxel[0] >> _SHIFT) + _BIAS
    by = wp.int64(voxel[1] >> _SHIFT) + _BIAS
    bz = wp.int64(voxel[2] >> _SHIFT) + _BIAS
    return (bx << _SHIFT_X) | (by << _SHIFT_Y) | bz


@wp.func
def home(key: wp.int64, mask: wp.int64) -> wp.int64:
    """First probe of ``key``: packed neighbours differ in few bits, so mix them all."""
    h = wp.uint64(key)
    h = (h ^ (h >> wp.uint64(30))) * _MIX1
    h = (h ^ (h >> wp.uint64(27))) * _MIX2
    h = h ^ (h >> wp.uint64(31))
    return wp.int64(h) & mask


@wp.func
def find_slot(index: BrickIndex, key: wp.int64) -> int:
    """Pool slot of brick ``key`` by linear probing, -1 if the brick is not stored."""
    at = home(key, index.mask)
    found = int(-1)
    probing = bool(True)
    while probing:
        k = index.keys[at]
        if k == key:
            found = index.slots[at]
            probing = False
        elif k == EMPTY:
            probing = False
        at = (at + wp.int64(1)) & index.mask
    return found


@wp.func
def within_reach(index: BrickIndex, p: wp.vec3d) -> bool:
    """Whether point ``p`` lies strictly within the table's reach (False for NaN): beyond
    it a brick key would wrap onto another brick, so the point is left to the host."""
    r = index.reach
    return wp.abs(p[0]) < r and wp.abs(p[1]) < r and wp.abs(p[2]) < r


@wp.func
def touch(index: BrickIndex, slot: int, tick: wp.int64):
    """Mark a brick as used in this batch; written once per batch, not once per point,
    so lookup threads do not fight over the stamps' cache lines."""
    if index.stamps[slot] != tick:
        index.stamps[slot] = tick


@wp.func
def voxel_stored(index: BrickIndex, slot: int, local: int) -> bool:
    """Whether voxel ``local`` of the brick in pool ``slot`` (-1: absent) is stored."""
    if slot < 0:
        return False
    return (index.valid[slot * VALID_WORDS + (local >> 5)] & bit_mask(local)) != wp.uint32(0)


@wp.func
def stored_slot(index: BrickIndex, voxel: wp.vec3i) -> int:
    """Pool slot of the brick holding ``voxel`` if the voxel is stored, else -1."""
    slot = find_slot(index, brick_key(voxel))
    if index.partial != 0:
        stored = voxel_stored(index, slot, cell_local_index(voxel, _SHIFT))
        if not stored:
            slot = -1
    return slot


@wp.func
def voxel_address(index: BrickIndex, slot: int, local: int) -> int:
    """Pool position of stored voxel ``local`` of the brick in ``slot``: a brick's stored
    voxels are packed in local order, so it is the brick's base plus the number of stored
    voxels before it, which in a whole brick is ``local`` itself."""
    if index.partial == 0:
        return index.base[slot] + local
    row = slot * VALID_WORDS
    word = local >> 5
    below = bit_mask(local) - wp.uint32(1)
    rank = int(wp.bit_count(index.valid[row + word] & below))
    for w in range(word):
        rank += int(wp.bit_count(index.valid[row + w]))
    return index.base[slot] + rank


@wp.func
def pooled_triple(pool: wp.array(dtype=Any), address: int) -> wp.vec3i:
    """Exemplar pixels (one per axis) of the stored voxel at pool position ``address``."""
    at = address * 3
    return wp.vec3i(int(pool[at]), int(pool[at + 1]), int(pool[at + 2]))


@wp.func
def voxel_triple(index: BrickIndex, pool: wp.array(dtype=Any), slot: int, local: int) -> wp.vec3i:
    """Exemplar pixels (one per axis) of a stored voxel."""
    return pooled_triple(pool, voxel_address(index, slot, local))


@wp.struct
class ExemplarColors:
    """The colors of each axis' exemplar, flattened (``pixel * channels + c``)."""

    x: wp.array(dtype=wp.float32)
    y: wp.array(dtype=wp.float32)
    z: wp.array(dtype=wp.float32)
    channels: int


@wp.func
def triple_sum(p: wp.vec3i, colors: ExemplarColors, c: int) -> wp.float32:
    """Channel ``c`` summed over a triple's three exemplar colors, in the engine's order."""
    n = colors.channels
    s = colors.x[p[0] * n + c] + colors.y[p[1] * n + c]
    return s + colors.z[p[2] * n + c]


@wp.func
def triple_channel(p: wp.vec3i, colors: ExemplarColors, c: int) -> wp.float32:
    """Channel ``c`` of a triple's color: the same float32 sum and division as
    ``Synthesizer.colors_of``, so the color is bit-identical to the engine's."""
    return triple_sum(p, colors, c) / wp.float32(3.0)


@wp.func
def flag_miss(i: int, missed: wp.array(dtype=wp.int32), miss_count: wp.array(dtype=wp.int32)):
    """Mark point ``i`` as missed, for the host to synthesize its voxels and finish it."""
    missed[i] = 1
    wp.atomic_add(miss_count, 0, 1)


@wp.kernel
def sample_nearest(
    offset: int,
    points: wp.array(dtype=wp.vec3d),
    index: BrickIndex,
    pool: wp.array(dtype=Any),
    colors: ExemplarColors,
    tick: wp.int64,
    out: wp.array2d(dtype=wp.float32),
    missed: wp.array(dtype=wp.int32),
    miss_count: wp.array(dtype=wp.int32),
):
    """Color of the voxel containing each point; points whose voxel is absent, or out of
    reach, are flagged."""
    i = offset + wp.tid()
    if not within_reach(index, points[i]):
        flag_miss(i, missed, miss_count)
        return
    voxel = floor_voxel(points[i])
    slot = stored_slot(index, voxel)
    if slot < 0:
        flag_miss(i, missed, miss_count)
        return
    touch(index, slot, tick)
    p = voxel_triple(index, pool, slot, cell_local_index(voxel, _SHIFT))
    for c in range(colors.channels):
        out[i, c] = triple_channel(p, colors, c)


@wp.kernel
def sample_trilinear(
    offset: int,
    points: wp.array(dtype=wp.vec3d),
    index: BrickIndex,
    pool: wp.array(dtype=Any),
    colors: ExemplarColors,
    tick: wp.int64,
    out: wp.array2d(dtype=wp.float32),
    missed: wp.array(dtype=wp.int32),
    miss_count: wp.array(dtype=wp.int32),
):
    """Trilinear blend of the 8 voxel centers around each point. Corners may lie in
    different bricks, so each corner finds its own brick: borders are seamless. Points
    with a corner not stored, or out of reach, are flagged."""
    i = offset + wp.tid()
    if not within_reach(index, points[i]):
        flag_miss(i, missed, miss_count)
        return
    q = points[i] - wp.vec3d(0.5, 0.5, 0.5)
    base = floor_voxel(q)
    t = q - wp.vec3d(wp.float64(base[0]), wp.float64(base[1]), wp.float64(base[2]))
    # Corners of one brick are consecutive in this order, so most skip the table search.
    addresses = wp.vector(dtype=wp.int32, length=8)  # pool positions, -1: not stored
    last_key = wp.int64(EMPTY)
    last_slot = int(-1)
    last_base = int(0)
    for corner in range(8):
        voxel = base + wp.vec3i((corner >> 2) & 1, (corner >> 1) & 1, corner & 1)
        key = brick_key(voxel)
        if key != last_key:
            last_key = key
            last_slot = find_slot(index, key)
            if last_slot >= 0:
                touch(index, last_slot, tick)
                last_base = index.base[last_slot]
        addresses[corner] = -1
        if last_slot >= 0:
            local = cell_local_index(voxel, _SHIFT)
            if index.partial == 0:  # voxel_address's first case, the base read once a brick
                addresses[corner] = last_base + local
            elif voxel_stored(index, last_slot, local):
                addresses[corner] = voxel_address(index, last_slot, local)
    if wp.min(addresses) < 0:
        flag_miss(i, missed, miss_count)
        return
    acc = wp.vector(dtype=wp.float64, length=MAX_CHANNELS)
    for corner in range(8):
        dx = (corner >> 2) & 1
        dy = (corner >> 1) & 1
        dz = corner & 1
        w = wp.where(dx == 1, t[0], wp.float64(1.0) - t[0])
        w *= wp.where(dy == 1, t[1], wp.float64(1.0) - t[1])
        w *= wp.where(dz == 1, t[2], wp.float64(1.0) - t[2])
        p = pooled_triple(pool, addresses[corner])
        for c in range(colors.channels):
            acc[c] += w * wp.float64(triple_sum(p, colors, c))
    # The blend of the sums divided once: the blend of the voxel colors, 21 divisions fewer.
    for c in range(colors.channels):
        out[i, c] = wp.float32(acc[c] / wp.float64(3.0))


@wp.kernel
def voxel_sums(
    slots: wp.array(dtype=wp.int32),
    index: BrickIndex,
    pool: wp.array(dtype=Any),
    colors: ExemplarColors,
    out: wp.array2d(dtype=wp.float32),
):
    """Three-color sum of every voxel of the bricks in pool ``slots`` (-1: absent), as the
    lookups compute it, for readers outside Warp (the Mitsuba plugin's traced and scalar
    lookups); NaN where not stored."""
    v = wp.tid()
    slot = slots[v // BRICK_VOXELS]
    if voxel_stored(index, slot, v % BRICK_VOXELS):
        p = voxel_triple(index, pool, slot, v % BRICK_VOXELS)
        for c in range(colors.channels):
            out[v, c] = triple_sum(p, colors, c)
    else:
        for c in range(colors.channels):
            out[v, c] = wp.nan


@wp.kernel
def insert_keys(keys: wp.array(dtype=wp.int64), slots: wp.array(dtype=wp.int32), index: BrickIndex):
    """Insert distinct new bricks into the table, one thread each: a probe claims a free
    entry by compare-and-swap, so threads whose probes collide take different entries. Where
    each key lands then depends on thread timing, but every key is found by
    :func:`find_slot` whatever the layout, so no lookup result does."""
    n = wp.tid()
    key = keys[n]
    at = home(key, index.mask)
    probing = bool(True)
    while probing:
        if wp.atomic_cas(index.keys, int(at), EMPTY, key) == EMPTY:
            index.slots[at] = slots[n]
            probing = False
        else:
            at = (at + wp.int64(1)) & index.mask


# The two payloads a brick pool holds (warptex.store): 16-bit pixel indices while every
# exemplar has at most 65536 pixels, else 32-bit. Declared here so that every build of the
# module, for the CPU, for CUDA or ahead of time, has both.
for _generic in (sample_nearest, sample_trilinear, voxel_sums):
    for _payload in (wp.uint16, wp.int32):
        wp.overload(_generic, {"pool": wp.array(dtype=_payload)})
del _generic, _payload
