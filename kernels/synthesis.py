"""Kernels of lazy, spatially deterministic solid synthesis (Dong 2008, section 5).

Voxels live in sparse blocks of 4^3; a block's 27 neighbours are found through a table
built by the host, so a kernel reads any voxel within four voxels of its own. Every voxel
stores a triple of exemplar pixel indices (one per axis). The exemplar of axis k spans
the volume axes (k+1, k+2) as its (first, second) pixel coordinates.

All arithmetic is on integers, so results are bit-identical on the CPU and on CUDA.
"""

import warp as wp

from kernels.common import (
    cell_local_index,
    floor_div,
    hash_cell,
    pixel_coords,
    pixel_index,
    plane_offset,
    wrap,
)

wp.set_module_options({"enable_backward": False})

# The voxel indexing below is spelled out for blocks of 4^3 (shifts by 2, 4 and 6, masks of
# 3, 3 x 3 x 3 neighbour blocks): another block size means rewriting it, not this constant.
BLOCK = 4
BLOCK_VOXELS = 64
assert BLOCK_VOXELS == BLOCK**3 == 64
_BLOCK_SHIFT = wp.constant(BLOCK.bit_length() - 1)  # BLOCK = 2^_BLOCK_SHIFT
MAX_DIMS = 12
PROJ_LIMIT = 2047  # projections are 12-bit, so a 3-plane distance fits in int32
TILE_SALT = 64  # hashes of tile shifts, apart from the jitter's octaves (salts 0-33)
BASIS_LIMIT = 127  # |basis| of the int8 PCA bases (warptex.candidates)
# Terms a float32 sum adds exactly in any order: |basis| <= 127 times features <= 3 * 255
# stay below 2^24 (see project_neighborhoods).
EXACT_ROW_TERMS = (1 << 24) // (BASIS_LIMIT * 3 * 255)

appearance_vector = wp.types.vector(length=MAX_DIMS, dtype=wp.int32)
"""A PCA-projected neighbourhood; unused trailing dimensions are zero."""

basis_row = wp.types.vector(length=MAX_DIMS, dtype=wp.float32)
"""One neighbourhood entry's basis coefficients, as floats holding small integers."""


@wp.struct
class LevelTables:
    """Exemplar data of one pyramid level for the three axes (concatenated sources)."""

    height: wp.vec3i
    width: wp.vec3i
    half: int  # N // 2
    nfeat: int
    shift: wp.vec3i  # projections are (basis . features) >> shift
    # Rows (top and bottom) and columns (left and right) no candidate holds, where a photo
    # does not tile: its seam is never continued (warptex.candidates._margins).
    margin_rows: wp.vec3i
    margin_cols: wp.vec3i
    k2: int  # 2D candidates searched per pixel
    k3: int  # 3D candidates searched per pixel
    feat_off: wp.vec3i
    feat: wp.array(dtype=wp.int32)
    basis_off: wp.vec3i
    basis: wp.array(dtype=basis_row)  # per source, N*N*F basis rows
    proj_off: wp.vec3i
    proj: wp.array(dtype=appearance_vector)
    cand2d_off: wp.vec3i
    cand2d_stride: int
    cand2d: wp.array(dtype=wp.int32)
    cand3d_off: wp.vec3i  # per axis: where the role owned by that axis starts
    cand3d_stride: int
    cand3d: wp.array(dtype=wp.int32)
    count3d_off: wp.vec3i
    count3d: wp.array(dtype=wp.int32)


@wp.func
def block_local(i: int) -> wp.vec3i:
    """Position of voxel ``i`` (a flat index, so non-negative) inside its 4^3 block.

    Shifts and masks rather than ``//`` and ``%``, which Warp rounds for negative
    operands too: neighbour lookups are the engine's most frequent operation."""
    return wp.vec3i((i >> 4) & 3, (i >> 2) & 3, i & 3)


@wp.func
def voxel_world(coords: wp.array(dtype=wp.vec3i), i: int) -> wp.vec3i:
    """Coordinates of work voxel ``i``: its block's corner plus its place in the block."""
    return coords[i >> 6] * BLOCK + block_local(i)


@wp.func
def parent_voxel(p: wp.vec3i) -> wp.vec3i:
    """The voxel one level coarser that voxel ``p`` inherits from (section 5.1, p >> 1,
    rounding down at negative coordinates too)."""
    return wp.vec3i(p[0] >> 1, p[1] >> 1, p[2] >> 1)


@wp.func
def neighbor_block(dx: int, dy: int, dz: int) -> int:
    """Column of a work block's block-neighbour table for the block at offset
    ``(dx, dy, dz)`` (each -1, 0 or 1): the 3 x 3 x 3 neighbours, x slowest."""
    return (dx + 1) * 9 + (dy + 1) * 3 + dz + 1


@wp.func
def halo_side(half: int) -> int:
    """Voxels along a side of a halo block: a work block with ``half`` voxels more on
    either side (warptex.synthesis gathers halo blocks of this side)."""
    return BLOCK + 2 * half


@wp.func
def neighbor_in_block(nbr: wp.array2d(dtype=wp.int32), block: int, local: wp.vec3i,
                      d: wp.vec3i) -> int:
    """Flat index of the voxel at offset ``d`` (|d| <= 4) from position ``local`` of work
    block ``block``, -1 if absent."""
    p = local + d
    slot = nbr[block, neighbor_block(p[0] >> 2, p[1] >> 2, p[2] >> 2)]
    if slot < 0:
        return -1
    return (slot << 6) + cell_local_index(p, _BLOCK_SHIFT)


@wp.func
def neighbor_voxel(nbr: wp.array2d(dtype=wp.int32), i: int, d: wp.vec3i) -> int:
    """Flat index of the voxel at offset ``d`` (|d| <= 4) from voxel ``i``, -1 if absent."""
    return neighbor_in_block(nbr, i >> 6, block_local(i), d)


@wp.func
def shift_pixel(pix: int, du: int, dv: int, height: int, width: int) -> int:
    """Exemplar pixel ``pix`` moved by ``(du, dv)``, wrapping around the exemplar."""
    uv = pixel_coords(pix, width)
    return pixel_index(uv[0] + du, uv[1] + dv, height, width)


@wp.func
def step_pixel(pix: int, du: int, dv: int, height: int, width: int) -> int:
    """``shift_pixel`` for steps of at most one row and column (|du|, |dv| <= 1): one
    division instead of three, as wrapping takes at most one correction per axis."""
    v = pix % width + dv  # pix >= 0, so % is the column
    p = pix + du * width + dv
    if v < 0:
        p += width
    if v >= width:
        p -= width
    size = height * width
    if p < 0:
        p += size
    if p >= size:
        p -= size
    return p


@wp.func
def bump_sum(pos: wp.vec3i, seed: int, jitter: int, octave: int, cell: int, rmin: int,
             rrange: int, amin: int, arange: int) -> wp.vec3i:
    """One octave of the random warp of section 5.1 ("Jitter"), in 1/256 voxel units.

    Each lattice cell of ``cell`` voxels holds one smooth bump of random centre, radius
    (``rmin``..``rmin + rrange`` voxels), amplitude (scaled by ``jitter``/256) and
    direction. The bump profile (1 - r^2/R^2)^3 stands in for the paper's Gaussian: it
    has compact support and is exact in integers, so CPU and CUDA agree bit for bit.
    """
    fine = wp.vec3i(pos[0] * 256, pos[1] * 256, pos[2] * 256)
    cx = floor_div(pos[0], cell)
    cy = floor_div(pos[1], cell)
    cz = floor_div(pos[2], cell)
    sx = wp.int64(0)
    sy = wp.int64(0)
    sz = wp.int64(0)
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            for dz in range(-1, 2):
                h = hash_cell(cx + dx, cy + dy, cz + dz, seed, octave)
                h1 = hash_cell(cx + dx, cy + dy, cz + dz, seed, octave + 16)
                span = wp.uint32(cell * 256)
                ox = (cx + dx) * cell * 256 + int(h % span)
                oy = (cy + dy) * cell * 256 + int((h >> wp.uint32(8)) % span)
                oz = (cz + dz) * cell * 256 + int((h >> wp.uint32(16)) % span)
                rad = wp.int64(rmin * 256 + int(h1 % wp.uint32(rrange * 256 + 1)))
                ex = wp.int64(fine[0] - ox)
                ey = wp.int64(fine[1] - oy)
                ez = wp.int64(fine[2] - oz)
                r2 = ex * ex + ey * ey + ez * ez
                if r2 < rad * rad:
                    t = wp.int64(65536) - (r2 * wp.int64(65536)) // (rad * rad)
                    w = (((t * t) >> wp.int64(16)) * t) >> wp.int64(16)
                    pick = int((h1 >> wp.uint32(12)) % wp.uint32(arange * 256 + 1))
                    amp = wp.int64(amin * 256 + pick)
                    amp = (amp * wp.int64(jitter)) >> wp.int64(8)
                    h2 = hash_cell(cx + dx, cy + dy, cz + dz, seed, octave + 32)
                    dirx = wp.int64(int(h2 % wp.uint32(513)) - 256)
                    diry = wp.int64(int((h2 >> wp.uint32(10)) % wp.uint32(513)) - 256)
                    dirz = wp.int64(int((h2 >> wp.uint32(20)) % wp.uint32(513)) - 256)
                    sx += (amp * dirx * w) >> wp.int64(24)
                    sy += (amp * diry * w) >> wp.int64(24)
                    sz += (amp * dirz * w) >> wp.int64(24)
    return wp.vec3i(int(sx), int(sy), int(sz))


@wp.func
def warp_offset(pos: wp.vec3i, seed: int, jitter: int) -> wp.vec3i:
    """Integer displacement of the continuous random warp (section 5.1, "Jitter").

    Two octaves of bumps where the paper sums about 200 Gaussians: lattice cells of 16 and
    6 voxels, radii 6-14 and 2-5 voxels, amplitudes 2-6 and 1-3 voxels times ``jitter``
    (in 1/256). The small-scale octave is the stronger for its size, not in voxels as the
    paper's A_i, and directions are random in a cube rather than normalized; the paper
    says exact values do not matter, only that the warp randomizes.
    """
    s = bump_sum(pos, seed, jitter, 0, 16, 6, 8, 2, 4)
    s += bump_sum(pos, seed, jitter, 1, 6, 2, 3, 1, 2)
    return wp.vec3i((s[0] + 128) >> 8, (s[1] + 128) >> 8, (s[2] + 128) >> 8)


@wp.func
def tile_shift(p: wp.vec3i, n: int, t: LevelTables, seed: int) -> wp.vec2i:
    """A hashed offset of the slab tile holding ``p`` (N voxels along x, one exemplar along
    y and z), in x exemplar pixels: tiles then no longer repeat every exemplar width."""
    h = hash_cell(floor_div(p[0], n), floor_div(p[1], t.height[0]), floor_div(p[2], t.width[0]),
                  seed, TILE_SALT)
    return wp.vec2i(int(h % wp.uint32(t.height[0])),
                    int((h >> wp.uint32(16)) % wp.uint32(t.width[0])))


@wp.kernel
def initialize(
    first: int,
    coords: wp.array(dtype=wp.vec3i),
    t: LevelTables,
    seed: int,
    jitter: int,
    shifted_tiles: int,
    triples: wp.array(dtype=wp.vec3i),
):
    """Tiling of the x exemplar's candidate slab (section 4.3), warped by the jitter; with
    ``shifted_tiles`` each tile shows the slab shifted by its own offset."""
    i = first + wp.tid()
    p = voxel_world(coords, i)
    p = p + warp_offset(p, seed, jitter)
    n = 2 * t.half + 1
    depth = wrap(p[0], n) - t.half
    shift = wp.vec2i(0, 0)
    if shifted_tiles != 0:
        shift = tile_shift(p, n, t, seed)
    own = pixel_index(p[1] + shift[0], p[2] + shift[1], t.height[0], t.width[0])
    best = t.cand3d_off[0] + own * t.cand3d_stride * 2  # the pixel's first 3D candidate
    q = shift_pixel(t.cand3d[best], 0, depth, t.height[1], t.width[1])
    r = shift_pixel(t.cand3d[best + 1], depth, 0, t.height[2], t.width[2])
    triples[i] = wp.vec3i(own, q, r)


@wp.kernel
def upsample(
    first: int,
    coords: wp.array(dtype=wp.vec3i),
    parent_slot: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.vec3i),
    parent_width: wp.vec3i,
    t: LevelTables,
    triples: wp.array(dtype=wp.vec3i),
):
    """Coordinate inheritance (section 5.1, "Upsampling"): child = 2 * parent + offset."""
    i = first + wp.tid()
    slot = parent_slot[i // BLOCK_VOXELS]
    if slot < 0:  # a block no correction reads: its parents were not synthesized
        return
    p = voxel_world(coords, i)
    src = parent[slot * BLOCK_VOXELS + cell_local_index(parent_voxel(p), _BLOCK_SHIFT)]
    out = wp.vec3i(0, 0, 0)
    for k in range(3):
        uv = pixel_coords(src[k], parent_width[k])
        du = p[(k + 1) % 3] & 1
        dv = p[(k + 2) % 3] & 1
        out[k] = pixel_index(2 * uv[0] + du, 2 * uv[1] + dv, t.height[k], t.width[k])
    triples[i] = out


@wp.kernel
def voxel_features(
    first: int, triples: wp.array(dtype=wp.vec3i), t: LevelTables,
    feats: wp.array(dtype=wp.float32)
):
    """Matching features of each voxel: the sum of its three exemplar features."""
    i = first + wp.tid()
    tri = triples[i]
    for c in range(t.nfeat):
        s = int(0)
        for k in range(3):
            s += t.feat[t.feat_off[k] + tri[k] * t.nfeat + c]
        feats[i * t.nfeat + c] = float(s)


@wp.kernel
def mark_parents(
    first: int,
    need: wp.array(dtype=wp.uint8),
    coords: wp.array(dtype=wp.vec3i),
    parent_block: wp.array(dtype=wp.int32),
    parents: wp.array(dtype=wp.uint8),
):
    """Flag, one level up, the parent of every voxel ``need`` marks (section 5.1: voxel
    v's parent is v >> 1, in block ``parent_block`` of its block). Threads may write the
    same 1 to a voxel; the result is the same."""
    i = first + wp.tid()
    if need[i] != wp.uint8(0):
        local = cell_local_index(parent_voxel(voxel_world(coords, i)), _BLOCK_SHIFT)
        parents[parent_block[i >> 6] * BLOCK_VOXELS + local] = wp.uint8(1)


@wp.kernel
def spread_need(
    first: int,
    corrected: wp.array(dtype=wp.int32),
    nbr: wp.array2d(dtype=wp.int32),
    shape: wp.array(dtype=wp.vec3i),
    before: wp.array(dtype=wp.uint8),
):
    """Dependency mask (section 5.2), one correction step undone: every voxel that a
    voxel corrected by the step reads (``shape``: the offsets a correction reads) is
    needed before it. Threads may write the same 1 to a voxel; the result is the same."""
    i = corrected[first + wp.tid()]
    for n in range(shape.shape[0]):
        j = neighbor_voxel(nbr, i, shape[n])
        if j >= 0:
            before[j] = wp.uint8(1)


@wp.kernel
def gather_halos(
    first: int,
    lo: int,
    blocks: wp.array(dtype=wp.int32),
    nbr: wp.array2d(dtype=wp.int32),
    src: wp.array(dtype=wp.vec3i),
    feats: wp.array(dtype=wp.float32),
    t: LevelTables,
    halos: wp.array(dtype=wp.float32),
    halo_src: wp.array(dtype=wp.vec3i),
):
    """Features and triples of work blocks ``blocks`` with a halo of N // 2 voxels on
    every side, in a dense (4 + 2 * half)^3 layout: projection and correction then address
    neighbours with plain strides instead of a block-neighbour lookup per neighbour
    (section 5.1). Absent voxels hold -1, which no feature sum or pixel takes. One thread
    fills one z row of a halo block; block ``blocks[q]`` goes to halo block ``q - lo``, ``lo``
    being the first block of the chunk gathered."""
    side = halo_side(t.half)
    row = first + wp.tid()
    q = row // (side * side)
    r = row - q * side * side
    px = r // side - t.half
    py = r - (r // side) * side - t.half
    # A row crosses at most three blocks along z: one table entry each, not one per voxel.
    pre = neighbor_block(px >> 2, py >> 2, 0)
    lxy = ((px & 3) << 4) + ((py & 3) << 2)
    out = ((q - lo) * side * side + r) * side * t.nfeat
    for z in range(side):
        pz = z - t.half
        slot = nbr[blocks[q], pre + (pz >> 2)]
        j = (slot << 6) + lxy + (pz & 3)
        tri = wp.vec3i(-1, -1, -1)
        if slot >= 0:
            tri = src[j]
        halo_src[out // t.nfeat + z] = tri
        for c in range(t.nfeat):
            v = float(-1.0)
            if slot >= 0:
                v = feats[j * t.nfeat + c]
            halos[out + z * t.nfeat + c] = v


@wp.func
def halo_strides(half: int) -> wp.vec3i:
    """Index steps along x, y, z in a halo block."""
    side = halo_side(half)
    return wp.vec3i(side * side, side, 1)


@wp.func
def plane_strides(half: int, k: int) -> wp.vec2i:
    """Halo index steps along the two axes of the plane of axis k (see plane_offset)."""
    s = halo_strides(half)
    return wp.vec2i(s[(k + 1) % 3], s[(k + 2) % 3])


@wp.func
def halo_voxel_of(halo_of: wp.array(dtype=wp.int32), i: int, half: int) -> int:
    """Index of work voxel ``i`` in the halo block ``halo_of`` its block."""
    side = halo_side(half)
    p = block_local(i) + wp.vec3i(half, half, half)
    return halo_of[i >> 6] * side * side * side + wp.dot(p, halo_strides(half))


@wp.func
def halo_voxel(halos: wp.array(dtype=wp.float32), j: int, nfeat: int, own: int) -> int:
    """Halo voxel ``j``, or ``own`` (the centre) where the voxel is absent."""
    if halos[j * nfeat] < 0.0:
        return own
    return j


@wp.func
def entry_sum(t: LevelTables, halos: wp.array(dtype=wp.float32), w: int, j: int) -> basis_row:
    """Basis rows ``w...`` times the features of halo voxel ``j``: one neighbourhood entry."""
    nf = t.nfeat
    s = t.basis[w] * halos[j * nf]
    for c in range(1, nf):
        s += t.basis[w + c] * halos[j * nf + c]
    return s


@wp.func
def project_clamp(acc: appearance_vector, shift: int) -> appearance_vector:
    """A projection's integer sums scaled down by ``2^shift`` to 12 bits (``PROJ_LIMIT``),
    so that a distance over the three planes fits in int32."""
    for d in range(MAX_DIMS):
        acc[d] = wp.clamp(acc[d] >> shift, -PROJ_LIMIT, PROJ_LIMIT)
    return acc


@wp.kernel
def project_neighborhoods(
    first: int,
    active: wp.array(dtype=wp.int32),
    halo_of: wp.array(dtype=wp.int32),
    halos: wp.array(dtype=wp.float32),
    t: LevelTables,
    qproj: wp.array(dtype=appearance_vector),
):
    """PCA projection of a voxel's current N x N neighbourhoods in the planes of the three
    axes (section 5.1), read from the halo block ``halo_of`` its block.

    Each row of a neighbourhood is summed in float32, which vectorizes on CPUs, and is
    still exact integer arithmetic: a row's N * F terms of |basis| <= 127 times features
    <= 3 * 255 stay below 2^24 (N * F <= EXACT_ROW_TERMS, which the engine checks), so any
    order of the additions gives the same sum. Rows add up in int32. The three planes
    accumulate side by side: independent sums keep the CPU's floating-point units busy.
    """
    i = active[first + wp.tid()]
    own = halo_voxel_of(halo_of, i, t.half)
    sx = halo_strides(t.half)[0]  # along z the stride is 1
    sy = halo_strides(t.half)[1]
    h = t.half
    acc0 = appearance_vector()
    acc1 = appearance_vector()
    acc2 = appearance_vector()
    w = int(0)  # entry (a, b) of every plane: basis rows basis_off[k] + w ...
    for a in range(-h, h + 1):
        row0 = basis_row()
        row1 = basis_row()
        row2 = basis_row()
        for b in range(-h, h + 1):
            # The exemplar of axis k spans volume axes (k+1, k+2): see plane_offset.
            j0 = halo_voxel(halos, own + a * sy + b, t.nfeat, own)
            j1 = halo_voxel(halos, own + a + b * sx, t.nfeat, own)
            j2 = halo_voxel(halos, own + a * sx + b * sy, t.nfeat, own)
            row0 += entry_sum(t, halos, t.basis_off[0] + w, j0)
            row1 += entry_sum(t, halos, t.basis_off[1] + w, j1)
            row2 += entry_sum(t, halos, t.basis_off[2] + w, j2)
            w += t.nfeat
        acc0 += appearance_vector(row0)
        acc1 += appearance_vector(row1)
        acc2 += appearance_vector(row2)
    qproj[i * 3] = project_clamp(acc0, t.shift[0])
    qproj[i * 3 + 1] = project_clamp(acc1, t.shift[1])
    qproj[i * 3 + 2] = project_clamp(acc2, t.shift[2])


@wp.func
def appearance_distance(t: LevelTables, qproj: wp.array(dtype=appearance_vector), i: int,
                        k: int, pix: int) -> int:
    """Squared distance between a voxel's projected plane k and exemplar pixel ``pix``."""
    e = t.proj[t.proj_off[k] + pix] - qproj[i * 3 + k]
    return wp.dot(e, e)


@wp.func
def best_2d_candidate(
    halo_src: wp.array(dtype=wp.vec3i),
    qproj: wp.array(dtype=appearance_vector),
    t: LevelTables,
    i: int,
    centre: int,
    k: int,
) -> int:
    """Step 1 of the two-step search (section 5.1): best k-coherent 2D candidate in the
    plane of axis k, gathered from the 3 x 3 in-plane neighbours (halo voxels around
    ``centre``), shifted back."""
    h = t.height[k]
    w = t.width[k]
    s = plane_strides(t.half, k)
    best = int(-1)
    best_d = int(0)
    last = int(-1)
    for da in range(-1, 2):
        for db in range(-1, 2):
            pix = halo_src[centre + da * s[0] + db * s[1]][k]
            if pix < 0:
                pix = halo_src[centre][k]
            p = step_pixel(pix, -da, -db, h, w)
            # Coherent neighbours often agree on p: its candidates were just compared, and
            # an equal distance never replaces the best, so skipping them changes nothing.
            if p != last:
                last = p
                for c in range(t.k2):
                    cand = t.cand2d[t.cand2d_off[k] + p * t.cand2d_stride + c]
                    dist = appearance_distance(t, qproj, i, k, cand)
                    if best < 0 or dist < best_d:
                        best = cand
                        best_d = dist
    return best


@wp.func
def shifted_triple(tri: wp.vec3i, d: wp.vec3i, t: LevelTables) -> wp.vec3i:
    """The triple that continues all three exemplar patches of the voxel at offset ``d``
    (|d| <= 1), which holds ``tri``: exemplar j spans the volume axes (j+1, j+2)."""
    out = wp.vec3i(0, 0, 0)
    for j in range(3):
        out[j] = step_pixel(tri[j], -d[(j + 1) % 3], -d[(j + 2) % 3], t.height[j], t.width[j])
    return out


@wp.func
def clear_of_margins(t: LevelTables, tri: wp.vec3i) -> bool:
    """Whether all three pixels of ``tri`` lie outside their exemplars' margins, as every
    pre-computed candidate does."""
    clear = True
    for k in range(3):
        if t.margin_rows[k] > 0 or t.margin_cols[k] > 0:
            uv = pixel_coords(tri[k], t.width[k])
            if uv[0] < t.margin_rows[k] or uv[0] >= t.height[k] - t.margin_rows[k]:
                clear = False
            if uv[1] < t.margin_cols[k] or uv[1] >= t.width[k] - t.margin_cols[k]:
                clear = False
    return clear


@wp.func
def triple_distance(t: LevelTables, qproj: wp.array(dtype=appearance_vector), i: int,
                    tri: wp.vec3i) -> int:
    """Squared distance between a voxel's projected 3-neighbourhood and triple ``tri``'s."""
    dist = int(0)
    for j in range(3):
        dist += appearance_distance(t, qproj, i, j, tri[j])
    return dist


@wp.kernel
def correct(
    first: int,
    active: wp.array(dtype=wp.int32),
    halo_of: wp.array(dtype=wp.int32),
    halo_src: wp.array(dtype=wp.vec3i),
    qproj: wp.array(dtype=appearance_vector),
    t: LevelTables,
    dst: wp.array(dtype=wp.vec3i),
):
    """Correction (section 5.1): replace the triple by the best matching 3D candidate.

    Step 2 of the two-step search gathers the 3D candidates of the three best 2D pixels
    and compares whole 3-neighbourhoods; the in-plane neighbours' triples, shifted,
    compete with them. Strict comparisons in a fixed loop order make the first best win,
    so ties resolve identically everywhere. Voxels not listed in ``active`` (the step's
    voxels, of its sub-pass only) keep the value ``dst`` holds. Triples are read from the
    halo blocks that the projection read.
    """
    i = active[first + wp.tid()]
    centre = halo_voxel_of(halo_of, i, t.half)
    best = halo_src[centre]
    best_d = int(-1)
    for k in range(3):
        own = best_2d_candidate(halo_src, qproj, t, i, centre, k)
        own_d = appearance_distance(t, qproj, i, k, own)
        k1 = (k + 1) % 3
        k2 = (k + 2) % 3
        n3 = wp.min(t.k3, t.count3d[t.count3d_off[k] + own])
        for c in range(n3):
            e = t.cand3d_off[k] + (own * t.cand3d_stride + c) * 2
            q = t.cand3d[e]
            r = t.cand3d[e + 1]
            dist = own_d + appearance_distance(t, qproj, i, k1, q)
            dist += appearance_distance(t, qproj, i, k2, r)
            if best_d < 0 or dist < best_d:
                best_d = dist
                tri = wp.vec3i(0, 0, 0)
                tri[k] = own
                tri[k1] = q
                tri[k2] = r
                best = tri
    # 3D coherence, beyond section 5.1: each neighbour in the three planes offers its own
    # triple shifted to continue here, coherent with it in all three exemplars at once.
    # These neighbours lie inside the 3-neighbourhood, so dependencies do not grow.
    for k in range(3):
        s = plane_strides(t.half, k)
        for n in range(9):
            da = n // 3 - 1
            db = n % 3 - 1
            # A face neighbour lies in two planes: the first offers it (a repeat never wins).
            seen = n == 4 or (k == 1 and db == 0) or (k == 2 and (da == 0 or db == 0))
            if not seen:
                tri = halo_src[centre + da * s[0] + db * s[1]]
                if tri[0] >= 0:
                    shifted = shifted_triple(tri, plane_offset(k, da, db), t)
                    # Continuing a patch across a margin would copy the photo's seam.
                    if clear_of_margins(t, shifted):
                        dist = triple_distance(t, qproj, i, shifted)
                        if best_d < 0 or dist < best_d:
                            best_d = dist
                            best = shifted
    dst[i] = best
