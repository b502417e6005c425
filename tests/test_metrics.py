"""Quality metrics (Dong 2008, section 6.3) on volumes whose answer is known."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from warptex import metrics
from warptex.exemplar import Exemplar, wrapping_edges


def _exemplar() -> np.ndarray:
    rng = np.random.default_rng(0)
    base = rng.random((8, 8, 3)).astype(np.float32)
    return np.kron(base, np.ones((4, 4, 1), np.float32))  # 32 x 32 blocky structure


def test_axis_slices_are_oriented_like_the_exemplar():
    vol = np.arange(2 * 3 * 4).reshape(2, 3, 4, 1).astype(np.float32)
    # Axis 0 slices span (y, z); axis 1 slices span (z, x); axis 2 slices span (x, y).
    assert metrics.axis_slices(vol, 0, 1)[0].shape == (3, 4, 1)
    assert metrics.axis_slices(vol, 1, 1)[0].shape == (4, 2, 1)
    assert metrics.axis_slices(vol, 2, 1)[0].shape == (2, 3, 1)
    assert metrics.axis_slices(vol, 1, 1)[0][2, 1, 0] == vol[1, 0, 2, 0]


def test_extrusion_is_perfect_on_its_axis_only():
    ex = _exemplar()
    vol = metrics.extrusion(ex, 32, axis=2)
    assert np.array_equal(metrics.axis_slices(vol, 2, 1)[0], ex)
    assert metrics.neighborhood_energy(vol, ex, 2) == 0.0
    assert metrics.neighborhood_energy(vol, ex, 0) > 0.05
    assert metrics.sliced_wasserstein(vol, ex, 2) < metrics.sliced_wasserstein(vol, ex, 0)


def test_extrusion_stacks_along_z_unless_told_otherwise():
    ex = _exemplar()
    vol = metrics.extrusion(ex, 4)
    assert vol.shape == (32, 32, 4, 3)
    assert all(np.array_equal(vol[:, :, k], ex) for k in range(4))


def test_iid_noise_draws_every_exemplar_pixel():
    """The last pixel too: two pixels, 64 draws."""
    two = np.array([[[0.0], [1.0]]], np.float32)
    assert set(np.unique(metrics.iid_noise(two, (4, 4, 4)))) == {0.0, 1.0}


def test_slices_as_wide_as_a_patch_are_measured():
    """A 5 x 5 slice holds one 5 x 5 patch: measured, not refused."""
    ex = _exemplar()
    energy = metrics.neighborhood_energy(metrics.iid_noise(ex, (5, 5, 5)), ex, 0, size=5)
    assert np.isfinite(energy) and energy > 0


def test_noise_scores_badly_on_every_axis():
    ex = _exemplar()
    noise = metrics.iid_noise(ex, (32, 32, 32))
    tiled = metrics.extrusion(ex, 32, axis=0)
    for axis in range(3):
        assert metrics.neighborhood_energy(noise, ex, axis) > 0.3
    assert metrics.neighborhood_energy(tiled, ex, 0) == 0.0
    assert metrics.sliced_wasserstein(noise, ex, 0) > metrics.sliced_wasserstein(tiled, ex, 0)


def _slice(vol: np.ndarray, axis: int, i: int) -> np.ndarray:
    """Slice i across ``axis``, read like the exemplar of that axis, written out by hand:
    axis 0 -> (y, z), axis 1 -> (z, x), axis 2 -> (x, y)."""
    if axis == 0:
        return vol[i]
    return vol[:, i].transpose(1, 0, 2) if axis == 1 else vol[:, :, i]


def _energy_by_hand(vol, ex, axis, size):
    h, w, c = ex.shape
    rows = [(np.arange(i, i + size) % h)[:, None] for i in range(h)]
    cols = [(np.arange(j, j + size) % w)[None, :] for j in range(w)]
    ex_patches = np.array([ex[r, q].ravel() for r in rows for q in cols], np.float64)
    best = []
    for i in range(vol.shape[axis]):
        s = _slice(vol, axis, i)
        for r in range(0, s.shape[0] - size + 1, 2):
            for q in range(0, s.shape[1] - size + 1, 2):
                patch = s[r:r + size, q:q + size].ravel().astype(np.float64)
                best.append(((ex_patches - patch) ** 2).sum(axis=1).min())
    var = ex.reshape(-1, c).astype(np.float64).var(axis=0).sum()
    return np.mean(best) / (size * size * var)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_neighborhood_energy_equals_a_brute_force_reference(axis):
    rng = np.random.default_rng(0)
    ex = rng.random((8, 8, 3)).astype(np.float32)
    vol = rng.random((7, 9, 11, 3)).astype(np.float32)  # three sizes: an axis swap shows
    got = metrics.neighborhood_energy(vol, ex, axis, size=3, slices=100)  # every slice
    assert got == pytest.approx(_energy_by_hand(vol, ex, axis, 3), rel=1e-4)


def test_slices_of_the_exemplar_rolled_toroidally_have_zero_energy():
    """Exemplar patches wrap: a rolled exemplar is still made of exemplar patches."""
    rng = np.random.default_rng(1)
    ex = rng.random((16, 16, 3)).astype(np.float32)
    vol = metrics.extrusion(np.roll(ex, (5, 7), axis=(0, 1)), 16, axis=2)
    assert metrics.neighborhood_energy(vol, ex, 2) == 0.0


def test_exemplar_patches_do_not_wrap_across_a_seam():
    """A photo whose left and right edges differ (a ramp) is no torus: its patches stop at
    those edges, so a slice showing the ramp wrapped around costs energy, where the patches
    of an exemplar that tiles wrap as the paper's do."""
    rng = np.random.default_rng(6)
    ramp = (np.linspace(0.0, 1.0, 24)[None, :, None]
            + 0.05 * rng.random((20, 24, 3))).astype(np.float32)
    assert metrics.exemplar_patches(ramp, 5).shape == (20 * 20, 75)
    assert metrics.exemplar_patches(Exemplar(ramp), 5).shape == (20 * 20, 75)
    tiles = rng.random((20, 24, 3)).astype(np.float32)
    assert metrics.exemplar_patches(tiles, 5).shape == (20 * 24, 75)
    # Fewer than 5 unwrapped patches across a side: that side wraps anyway.
    assert metrics.exemplar_patches(ramp[:, :8], 5).shape == (20 * 8, 75)

    vol = metrics.extrusion(np.roll(ramp, 12, axis=1), 24, axis=2)
    assert metrics.neighborhood_energy(vol, ramp, 2) > 0.05
    vol = metrics.extrusion(np.roll(tiles, 12, axis=1), 24, axis=2)
    assert metrics.neighborhood_energy(vol, tiles, 2) == 0.0


def test_the_setting_tileable_decides_which_exemplar_patches_wrap():
    """tileable=True measures against the torus even where the photo has a seam, so the
    ramp wrapped around is then in the exemplar; False lets no patch wrap."""
    rng = np.random.default_rng(6)
    ramp = (np.linspace(0.0, 1.0, 24)[None, :, None]
            + 0.05 * rng.random((20, 24, 3))).astype(np.float32)
    tiles = rng.random((20, 24, 3)).astype(np.float32)
    for exemplar in (ramp, Exemplar(ramp)):
        assert metrics.exemplar_patches(exemplar, 5, tileable=True).shape == (20 * 24, 75)
    assert metrics.exemplar_patches(Exemplar(tiles), 5, tileable=False).shape == (16 * 20, 75)
    vol = metrics.extrusion(np.roll(ramp, 12, axis=1), 24, axis=2)
    assert metrics.neighborhood_energy(vol, ramp, 2, tileable=True) == 0.0
    assert metrics.worst_axis_energy(vol, ramp, tileable=True) == max(
        metrics.neighborhood_energy(vol, ramp, a, tileable=True) for a in range(3))
    assert metrics.worst_axis_energy(vol, ramp, tileable=False) > metrics.worst_axis_energy(
        vol, ramp, tileable=True)
    assert metrics.sliced_wasserstein(vol, ramp, 2, tileable=True) < metrics.sliced_wasserstein(
        vol, ramp, 2)
    with pytest.raises(ValueError, match="tileable must be"):
        metrics.neighborhood_energy(vol, ramp, 2, tileable="yes")


def test_energy_and_swd_do_not_depend_on_the_unit_of_the_colors():
    rng = np.random.default_rng(2)
    ex = rng.random((16, 16, 3)).astype(np.float32)
    vol = metrics.iid_noise(ex, (16, 16, 16))
    for metric in (metrics.neighborhood_energy, metrics.sliced_wasserstein):
        assert metric(4 * vol, 4 * ex, 0) == pytest.approx(metric(vol, ex, 0), rel=1e-4)
        # The unit, the exemplar's variance, over- and underflowed float32 at these.
        for unit in (np.float32(1e19), np.float32(1e-22)):
            assert metric(unit * vol, unit * ex, 0) == pytest.approx(metric(vol, ex, 0),
                                                                       rel=1e-3)


def test_histogram_distance_of_a_constant_volume_is_known():
    """All voxels in the lowest bin: per channel (1 - b0) + (1 - b0), b0 the share of the
    exemplar there; the channels are averaged."""
    rng = np.random.default_rng(3)
    ex = rng.random((16, 16, 3)).astype(np.float32)
    lo, hi = ex.reshape(-1, 3).min(0), ex.reshape(-1, 3).max(0)
    vol = np.broadcast_to(lo, (8, 8, 8, 3)).astype(np.float32)
    b0 = (ex.reshape(-1, 3) < lo + (hi - lo) / 16).mean(axis=0)
    expected = float(np.mean(2 * (1 - b0)))
    assert metrics.histogram_distance(vol, ex, 1) == pytest.approx(expected, rel=1e-6)
    assert metrics.histogram_distance(vol + 5.0, ex, 1) <= 2.0  # clipped into the last bin


def test_histogram_distance_of_a_constant_channel_counts_a_volume_that_leaves_it():
    """A channel the exemplar holds at one value is binned over a range of 1 from it: a
    volume at that value there scores 0 on it, one elsewhere in the range the maximum,
    2 (averaged over the three channels)."""
    ex = np.random.default_rng(9).random((16, 16, 3)).astype(np.float32)
    ex[..., 2] = 0.5
    vol = metrics.iid_noise(ex, (8, 8, 8))
    kept = metrics.histogram_distance(vol, ex, 0)
    vol[..., 2] = 0.9
    assert metrics.histogram_distance(vol, ex, 0) == pytest.approx(kept + 2 / 3)


def test_the_patch_measures_read_the_slices_asked_for():
    """``slices`` evenly spaced slices: two read the first and the last alone, flat here,
    where the default eight read the exemplar's copies between them too."""
    ex = np.random.default_rng(10).random((16, 16, 3)).astype(np.float32)
    vol = np.repeat(np.tile(ex, (2, 2, 1))[None], 16, axis=0)
    vol[[0, 15]] = ex.mean(axis=(0, 1))
    flat = np.broadcast_to(ex.mean(axis=(0, 1)), vol.shape)
    for metric in (metrics.sliced_wasserstein, metrics.completeness_energy,
                   metrics.neighborhood_energy):
        assert metric(vol, ex, 0, slices=2) == metric(flat, ex, 0, slices=2), metric
        assert metric(vol, ex, 0) < metric(flat, ex, 0), metric


def test_histogram_distance_reads_the_8_slices_across_its_axis():
    """Voxels hold their x index, 0 to 15, and the exemplar each of 0 to 15 once: one value
    to each of the 16 bins. Every slice across y or z holds every x: 0. The 8 slices across
    x are constant, 8 values of 16 at 1/8 each: 8 * 1/16 + 8 * 1/16 = 1. A histogram of
    every voxel gave 0 on every axis, one of the slices across x whatever the axis 1."""
    ex = np.arange(16, dtype=np.float32).reshape(4, 4, 1)
    vol = np.broadcast_to(np.arange(16, dtype=np.float32)[:, None, None, None],
                          (16, 16, 16, 1))
    assert [metrics.histogram_distance(vol, ex, axis) for axis in range(3)] == [1.0, 0.0, 0.0]


def test_repetition_score_counts_peaks_not_the_fall_off_of_large_features():
    """Smooth noise correlates with itself over its features' size, falling off from shift
    0 without a peak: low whatever ``exclude`` (the highest correlation past 8 pixels at
    all, the earlier score, was 0.7 for features of 8 pixels). A tiling peaks at its period
    and streaks along their length, both at 1."""
    rng = np.random.default_rng(4)
    noise = rng.standard_normal((256, 256))
    for sigma, exclude in ((3.0, 1), (8.0, 8)):
        smooth = gaussian_filter(noise, sigma, mode="wrap")
        assert metrics.repetition_score(smooth, exclude=exclude) < 0.35
    tile = gaussian_filter(rng.standard_normal((64, 64)), 3.0, mode="wrap")
    assert metrics.repetition_score(np.tile(tile, (4, 4))) == pytest.approx(1.0)
    streaks = np.tile(gaussian_filter(noise[0], 3.0, mode="wrap")[None], (256, 1))
    assert metrics.repetition_score(streaks) == pytest.approx(1.0)


def test_inputs_without_a_meaning_are_one_clear_error():
    """A flat exemplar has no variance to measure in (it gave 2.6e11), NaN colors gave NaN,
    and the other arguments failed deep inside or returned a number that meant nothing."""
    rng = np.random.default_rng(5)
    ex = rng.random((16, 16, 3)).astype(np.float32)
    vol = metrics.iid_noise(ex, (8, 8, 8))
    nan_vol = vol.copy()
    nan_vol[0, 0, 0, 0] = np.nan
    nan_ex = ex.copy()
    nan_ex[3, 4, 1] = np.nan
    cases = [
        (metrics.neighborhood_energy, (vol, np.full_like(ex, 0.5), 0), {}, "exemplar is constant"),
        # float32 rounding gives this one a variance of 1.5e-10, which made noise of scores
        (metrics.completeness_energy, (vol, np.full((32, 32, 3), 0.7, np.float32), 0), {},
         "exemplar is constant"),
        (metrics.sliced_wasserstein, (nan_vol, ex, 0), {}, "volume holds NaN"),
        (metrics.histogram_distance, (nan_vol, ex, 0), {}, "volume holds NaN"),
        (metrics.sliced_wasserstein, (vol, ex, 0), {"directions": 0}, "directions must be"),
        (metrics.neighborhood_energy, (vol, ex, 0), {"slices": 0}, "slices must be at least 1"),
        (metrics.neighborhood_energy, (vol, ex, 0), {"slices": 2.5}, "slices must be an integer"),
        (metrics.sliced_wasserstein, (vol, ex, 0), {"directions": 2.0}, "directions must be an"),
        (metrics.sliced_wasserstein, (vol, ex, 0), {"seed": "a"}, "seed must be an integer"),
        (metrics.histogram_distance, (vol, ex, 0), {"bins": 0}, "bins must be at least 1"),
        (metrics.axis_slices, (vol, 5), {}, "axis must be 0, 1 or 2"),
        (metrics.axis_slices, (vol, 0), {"count": 0}, "count .of slices. must be at least 1"),
        (metrics.extrusion, (ex, 4), {"axis": 3}, "axis must be 0, 1 or 2"),
        (metrics.repetition_score, (rng.random((64, 64)),), {"exclude": 2.5}, "exclude must be an"),
        (metrics.neighborhood_energy, (vol, ex, 0), {"size": 0}, "size .* positive integer"),
        (metrics.neighborhood_energy, (vol, ex, 1.0), {}, "axis must be 0, 1 or 2"),
        (metrics.neighborhood_energy, (vol[:0], ex, 0), {}, "too few or too small"),
        (metrics.repetition_score, (np.full((64, 64), np.nan),), {}, "image holds NaN"),
        (metrics.repetition_score, (rng.random((64, 64)),), {"exclude": -1}, "exclude must"),
        # One color everywhere, of channels that differ from each other.
        (metrics.neighborhood_energy, (vol, np.broadcast_to(np.float32([0.2, 0.5, 0.7]),
                                                            ex.shape), 0), {},
         "exemplar is constant"),
        (metrics.sliced_wasserstein, (vol, nan_ex, 0), {}, "exemplar holds NaN"),
        (metrics.iid_noise, (ex, (8, 8, 8, 8)), {}, "shape must be three positive ints"),
        (metrics.patches, (np.zeros((20, 8, 3)), 10), {}, r"size \(of the patches\) 10"),
        (metrics.patches, (np.zeros((20, 20, 3)), 4), {"stride": 0}, "stride must be at least 1"),
        (metrics.extrusion, (np.zeros((0, 8, 3)), 4), {}, "exemplar must be"),
    ]
    for metric, args, kwargs, message in cases:
        with pytest.raises(ValueError, match=message):
            metric(*args, **kwargs)
    with pytest.raises(TypeError, match=r"Exemplar\.load reads a file"):
        metrics.neighborhood_energy(vol, "granite_64.png", 0)
    from warptex.exemplar import Exemplar

    assert metrics.iid_noise(Exemplar(ex), (2, 2, 2)).shape == (2, 2, 2, 3)
    assert np.array_equal(metrics.extrusion(Exemplar(ex), 2), metrics.extrusion(ex, 2))


def _swd_by_hand(vol, ex, axis, size, directions, seed):
    """Sliced Wasserstein-1 written out: slice patches every 2 voxels, the exemplar's
    toroidal patches, projected on unit directions drawn as N(0, 1) columns."""
    h, w, c = ex.shape
    ex_patches = np.array([ex[(np.arange(i, i + size) % h)[:, None],
                              (np.arange(j, j + size) % w)[None, :]].ravel()
                           for i in range(h) for j in range(w)], np.float64)
    picks = np.unique(np.linspace(0, vol.shape[axis] - 1, min(8, vol.shape[axis])).astype(int))
    slice_patches = []
    for i in picks:
        s = vol[i] if axis == 0 else (vol[:, i].transpose(1, 0, 2) if axis == 1 else vol[:, :, i])
        for r in range(0, s.shape[0] - size + 1, 2):
            for q in range(0, s.shape[1] - size + 1, 2):
                slice_patches.append(s[r:r + size, q:q + size].ravel())
    slice_patches = np.array(slice_patches, np.float64)
    dirs = np.random.default_rng(seed).normal(size=(size * size * c, directions))
    dirs /= np.linalg.norm(dirs, axis=0)
    q = np.linspace(0.0, 1.0, 257)
    pa = np.quantile(slice_patches @ dirs, q, axis=0)
    pb = np.quantile(ex_patches @ dirs, q, axis=0)
    var = ex.reshape(-1, c).astype(np.float64).var(axis=0).sum()
    return np.mean(np.abs(pa - pb)) / np.sqrt(var)


@pytest.mark.parametrize("seed", [0, 3])
def test_sliced_wasserstein_equals_a_reference_on_unit_directions(seed):
    """Directions are unit vectors (unnormalized Gaussian columns scale the distance by
    about sqrt(size^2 C)) drawn from the seed given."""
    rng = np.random.default_rng(8)
    ex = rng.random((8, 8, 3)).astype(np.float32)
    vol = rng.random((7, 9, 11, 3)).astype(np.float32)
    got = metrics.sliced_wasserstein(vol, ex, 1, size=3, directions=16, seed=seed,
                                     tileable=True)
    assert got == pytest.approx(_swd_by_hand(vol, ex, 1, 3, 16, seed), rel=1e-4)
    other = metrics.sliced_wasserstein(vol, ex, 1, size=3, directions=16, seed=seed + 1,
                                       tileable=True)
    assert other != got


def test_iid_noise_follows_its_seed():
    ex = np.random.default_rng(9).random((16, 16, 3)).astype(np.float32)
    a, b = metrics.iid_noise(ex, (4, 4, 4), seed=1), metrics.iid_noise(ex, (4, 4, 4), seed=1)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, metrics.iid_noise(ex, (4, 4, 4), seed=2))
    # Every voxel is an exemplar pixel.
    pixels = {tuple(p) for p in ex.reshape(-1, 3)}
    assert all(tuple(v) in pixels for v in a.reshape(-1, 3))


def test_repetition_score_sees_a_pattern_repeated_along_one_axis_only():
    """Noise rows repeated every 32 columns: the shift (0, 32) matches exactly, although
    it moves along one axis only."""
    rng = np.random.default_rng(10)
    image = np.tile(rng.random((256, 32, 3)), (1, 8, 1))
    assert metrics.repetition_score(image) > 0.99
    assert metrics.repetition_score(image.transpose(1, 0, 2)) > 0.99


@pytest.mark.parametrize("period", [32, 64, 65, 72, 100, 128])
def test_repetition_score_sees_every_period_up_to_half_the_slice(period):
    """Noise tiles of any period up to half the 256-pixel slice, whole or cut at its edge,
    repeat exactly: 1. Before, only shifts up to a quarter counted, so periods of 65 to
    128 scored as low as 0.2 (a Kopf volume of 72^3, a 128 px exemplar stacked)."""
    tile = np.random.default_rng(period).random((period, period, 3))
    reps = -(-256 // period)
    image = np.tile(tile, (reps, reps, 1))[:256, :256]
    assert metrics.repetition_score(image) == pytest.approx(1.0, abs=1e-9)
    # Past half the slice a period is not seen: each shift's overlap holds no repeat.
    longer = np.tile(np.random.default_rng(0).random((160, 160, 3)), (2, 2, 1))[:256, :256]
    assert metrics.repetition_score(longer) < 0.2


def _repetition_by_hand(image: np.ndarray, exclude: int) -> float:
    """Every shift's correlation over the overlap (no wrap-around), normalized by the
    energies of both parts, for shifts up to half each side; the highest of those past
    ``exclude`` (each way) that no neighbouring shift exceeds."""
    from scipy import ndimage

    x = image - image.mean(axis=(0, 1))
    h, w = x.shape[:2]
    dys, dxs = np.arange(-(h // 2), h // 2 + 1), np.arange(-(w // 2), w // 2 + 1)
    score = np.zeros((len(dys), len(dxs)))
    for i, dy in enumerate(dys):
        for j, dx in enumerate(dxs):
            a = x[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)]
            b = x[max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)]
            score[i, j] = (a * b).sum() / np.sqrt((a**2).sum() * (b**2).sum())
    peak = score == ndimage.maximum_filter(score, size=3, mode="nearest")
    past = np.maximum(np.abs(dys)[:, None], np.abs(dxs)[None, :]) > exclude
    return float(np.where(peak & past, score, 0.0).max())


def test_a_constant_slice_repeats_nothing():
    """Its overlaps have no energy to normalize by: 0, as the docstring says."""
    assert metrics.repetition_score(np.zeros((64, 64))) == 0.0
    assert metrics.repetition_score(np.zeros((64, 64, 3))) == 0.0


def test_repetition_score_is_at_most_one():
    """An exactly tiled image scores 1, as the docstring says, not 1 + 1.6e-15."""
    from warptex.metrics import repetition_score

    image = np.tile(np.random.default_rng(1).random((8, 8, 3)), (9, 9, 1))[:64, :64]
    assert repetition_score(image, exclude=4) <= 1.0


@pytest.mark.parametrize("seed", [12, 14])
def test_repetition_score_equals_a_brute_force_reference(seed):
    """At every ``exclude`` from 0 (shift 0 alone left out) to 4: a shift of ``exclude``
    pixels or less each way never counts, and one just past it only where it is a peak.
    A faint period of 3 columns peaks at a shift of 3, counted up to ``exclude`` 2 only."""
    rng = np.random.default_rng(seed)
    image = gaussian_filter(rng.standard_normal((20, 26, 2)), (1.5, 1.0, 0))
    image += 0.5 * np.roll(image, (2, -3), axis=(0, 1))  # no mirror symmetry
    image += 0.3 * np.tile(rng.standard_normal((20, 3, 2)), (1, 9, 1))[:, :26]
    scores = [_repetition_by_hand(image, exclude) for exclude in range(5)]
    for exclude, expected in enumerate(scores):
        assert metrics.repetition_score(image, exclude=exclude) == pytest.approx(expected,
                                                                                rel=1e-9)
    assert scores[2] > scores[3] > 0.5 and scores[0] < 1.0


@pytest.mark.parametrize("shape", [(10, 13), (13, 10), (12, 16)])
def test_repetition_score_equals_the_reference_where_few_shifts_count(shape):
    """Small noise images at every ``exclude`` they allow, up to all but the last ring of
    shifts: which shifts are past ``exclude`` (farther than it along either axis), the last
    shift each way (half of a side, both signs) and peaks among the 8 neighbours then decide
    the score, not one high peak well inside the range."""
    rng = np.random.default_rng(sum(shape))
    image = gaussian_filter(rng.standard_normal((*shape, 2)), (0.7, 0.7, 0))
    for exclude in range(max(shape) // 2):
        assert metrics.repetition_score(image, exclude=exclude) == pytest.approx(
            _repetition_by_hand(image, exclude), rel=1e-9), exclude


@pytest.mark.parametrize("seed", [1, 11])
def test_repetition_score_equals_the_reference_at_the_last_ring_of_shifts(seed):
    """Noise of other shapes, where a peak lies on the last shift each way: its neighbours
    past the edge of the shifts are none (the reference's), not those across the other side
    (a wrapping peak filter scored 0.0 where the reference gives 0.005)."""
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(8, 20, 2))
    image = gaussian_filter(rng.standard_normal((*shape, 2)), (0.7, 0.7, 0))
    for exclude in range(max(shape) // 2):
        assert metrics.repetition_score(image, exclude=exclude) == pytest.approx(
            _repetition_by_hand(image, exclude), rel=1e-9), exclude


def test_repetition_score_sees_the_neighbours_of_shifts_along_a_side_mirrored():
    """Noise repeated at the shift (1, -3) (slightly smeared along the diagonal) correlates
    at (0, 4) too, on the fall-off of that excluded repetition: at (0, 4) the neighbour
    (-1, 3), the shift (1, -3) mirrored, correlates more, so (0, 4) is no peak. Taken for one
    where only shifts dy >= 0 were its neighbours, it scored 0.25 for an image with nothing
    past 3 pixels repeated."""
    rng = np.random.default_rng(0)
    noise = rng.standard_normal((64, 64))
    smeared = noise + np.roll(noise, (1, 1), axis=(0, 1))
    image = smeared + np.roll(smeared, (1, -3), axis=(0, 1))
    expected = _repetition_by_hand(image, 3)
    assert expected < 0.15
    assert metrics.repetition_score(image, exclude=3) == pytest.approx(expected, rel=1e-9)


def test_a_repetition_next_to_a_stronger_excluded_one_is_still_a_peak():
    """Noise repeated at 3 columns (excluded) and, fainter, at 5: the shift 5 is a peak
    among its 8 neighbours, at 0.6 / (1 + 1 + 0.36) = 0.25, though the shift 3, two
    columns away, correlates more (a 5 x 5 neighbourhood left it out, scoring 0.1)."""
    rng = np.random.default_rng(1)
    noise = rng.standard_normal((64, 64))
    image = noise + np.roll(noise, 3, axis=1) + 0.6 * np.roll(noise, 5, axis=1)
    expected = _repetition_by_hand(image, 3)
    assert expected == pytest.approx(0.6 / 2.36, abs=0.05)
    assert metrics.repetition_score(image, exclude=3) == pytest.approx(expected, rel=1e-9)


def test_wrapping_edges_wrap_a_seam_only_where_fewer_than_size_windows_fit():
    """Across a seam, a side of 2 size - 1 pixels still holds `size` unwrapped windows, one
    pixel less does not."""
    assert wrapping_edges((True, True), (9, 8), 5) == (False, True)
    assert wrapping_edges((True, False), (9, 9), 5) == (False, True)
    assert wrapping_edges((False, False), (40, 40), 5) == (True, True)
    rng = np.random.default_rng(6)
    ramp = (np.linspace(0.0, 1.0, 9)[None, :, None]
            + 0.05 * rng.random((20, 9, 3))).astype(np.float32)
    assert metrics.exemplar_patches(ramp, 5, tileable=False).shape == (16 * 5, 75)


def test_patches_larger_than_the_exemplar_are_refused():
    """A 20 x 20 patch of a 16 px exemplar wraps around it more than once: it gave an
    energy of 5, which meant nothing; now the exemplar is named too small."""
    rng = np.random.default_rng(13)
    ex = rng.random((16, 16, 3)).astype(np.float32)
    vol = metrics.iid_noise(ex, (24, 24, 24))
    for metric in (metrics.neighborhood_energy, metrics.sliced_wasserstein):
        with pytest.raises(ValueError, match="exemplar is 16 x 16: too small for 20 x 20"):
            metric(vol, ex, 0, size=20)
        assert metric(vol, ex, 0, size=16) > 0
    # Its narrow side decides: patches wrap around 8 rows however wide the rows are.
    narrow = rng.random((8, 24, 3)).astype(np.float32)
    for metric in (metrics.neighborhood_energy, metrics.completeness_energy,
                   metrics.sliced_wasserstein):
        with pytest.raises(ValueError, match="exemplar is 24 x 8: too small for 10 x 10"):
            metric(vol, narrow, 0, size=10)


def test_completeness_finds_every_exemplar_patch_and_misses_them_in_a_flat_volume():
    """The exemplar stacked along z holds each of its patches in every z-slice: 0; a volume
    of the exemplar's mean color is 1 (each wrapped patch's squared deviation from the mean,
    summed, is the variance); a reference that searches every pair agrees."""
    rng = np.random.default_rng(14)
    ex = gaussian_filter(rng.random((12, 12, 3)), (1, 1, 0), mode="wrap").astype(np.float32)
    stacked = metrics.extrusion(ex, 6, axis=2)
    assert metrics.completeness_energy(stacked, ex, 2, tileable=False) == 0.0
    flat = np.broadcast_to(ex.reshape(-1, 3).mean(0), (8, 8, 8, 3)).astype(np.float32)
    assert metrics.completeness_energy(flat, ex, 0, tileable=True) == pytest.approx(1.0,
                                                                                  rel=1e-5)
    vol = metrics.iid_noise(ex, (9, 10, 11), seed=3)
    mine = metrics.patches(ex, 3, wrap=True).astype(np.float64)
    theirs = np.concatenate([metrics.patches(s, 3) for s in metrics.axis_slices(vol, 1)])
    nearest = ((mine[:, None, :] - theirs[None].astype(np.float64)) ** 2).sum(-1).min(1)
    expected = nearest.mean() / (9 * ex.reshape(-1, 3).var(0).sum())
    got = metrics.completeness_energy(vol, ex, 1, size=3, tileable=True)
    assert got == pytest.approx(expected, rel=1e-5)
    # Coherence looks the other way: it differs, and both add up in the worst-axis sum.
    assert got != metrics.neighborhood_energy(vol, ex, 1, size=3, tileable=True)
    both = metrics.bidirectional_energy(vol, ex, tileable=True)
    assert both == pytest.approx(max(
        metrics.neighborhood_energy(vol, ex, a, tileable=True)
        + metrics.completeness_energy(vol, ex, a, tileable=True) for a in range(3)))


def test_bidirectional_energy_is_the_largest_sum_over_the_axes(monkeypatch):
    """Coherence worst across x, completeness across z: the worst axis' sum is z's, 0.7,
    not the sum of each measure's worst, 0.8; the setting tileable reaches both."""
    told = []

    def scored(values):
        return lambda volume, exemplar, axis, tileable: told.append(tileable) or values[axis]

    monkeypatch.setattr(metrics, "neighborhood_energy", scored([0.3, 0.1, 0.2]))
    monkeypatch.setattr(metrics, "completeness_energy", scored([0.1, 0.2, 0.5]))
    assert metrics.bidirectional_energy(None, None, tileable=False) == pytest.approx(0.7)
    assert metrics.worst_axis_energy(None, None, tileable=False) == 0.3
    assert told == [False] * 9


def test_repetition_and_patches_refuse_images_they_cannot_measure():
    """An empty image failed in NumPy's FFT or scored 0.0, a complex one was scored on its
    real part, and patches larger than the image failed in NumPy without naming size."""
    for shape in ((0, 40), (40, 40, 0)):
        with pytest.raises(ValueError, match="image must be"):
            metrics.repetition_score(np.zeros(shape))
    with pytest.raises(TypeError, match="real numbers, got complex128"):
        metrics.repetition_score(np.ones((40, 40), complex))
    # Booleans are scored as the numbers 0 and 1 (a diagonal repeats along itself).
    assert metrics.repetition_score(np.eye(40, dtype=bool)) == metrics.repetition_score(np.eye(40))
    with pytest.raises(ValueError, match=r"size \(of the patches\) 20 exceeds the image's 16 x 16"):
        metrics.patches(np.zeros((16, 16, 3)), 20)
    assert metrics.patches(np.zeros((16, 16, 3)), 20, wrap=True).shape == (256, 1200)


def test_flags_and_slice_indices_are_refused_not_taken_for_others():
    """wrap="no" wrapped, a slice index of 1.5 read slice 1, and one past the volume failed
    in NumPy without naming it."""
    with pytest.raises(ValueError, match="wrap must be True or False, got 'no'"):
        metrics.patches(np.zeros((16, 16, 3)), 4, wrap="no")
    with pytest.raises(ValueError, match="wrap must be True or False, got 1"):
        metrics.patches(np.zeros((16, 16, 3)), 4, wrap=(True, 1))
    volume = np.zeros((4, 5, 6, 3), np.float32)
    assert metrics.axis_slice(volume, 1, -5).shape == (6, 4, 3)
    for index in (1.5, 5, -6, True):
        with pytest.raises(ValueError, match=rf"index must be an integer within the volume's 5 "
                                             rf"slices along axis 1, got {index!r}"):
            metrics.axis_slice(volume, 1, index)
