"""Quality metrics (Dong 2008, section 6.3) on volumes whose answer is known."""

import numpy as np

from warptex import metrics


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


def test_noise_scores_badly_on_every_axis():
    ex = _exemplar()
    noise = metrics.iid_noise(ex, (32, 32, 32))
    tiled = metrics.extrusion(ex, 32, axis=0)
    for axis in range(3):
        assert metrics.neighborhood_energy(noise, ex, axis) > 0.3
    assert metrics.neighborhood_energy(tiled, ex, 0) == 0.0
    assert metrics.sliced_wasserstein(noise, ex, 0) > metrics.sliced_wasserstein(tiled, ex, 0)
