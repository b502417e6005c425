"""CPU and CUDA give the same results: point queries through the brick store (eviction
included), surface shells and baked texel points. Skipped without a GPU; the engine itself
is checked the same way in ``tests/test_synthesis.py`` and the plugin's ``cuda_ad_rgb``
lookups in ``tests/test_plugin.py``. ``benchmarks/gpu_checks.sh`` runs them on a lent GPU
machine."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

pytestmark = pytest.mark.skipif(
    "not __import__('warp').get_cuda_device_count()", reason="no CUDA device: CPU-only machine"
)


@pytest.mark.parametrize("whole_bricks", [True, False])
@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
def test_queries_agree_bit_for_bit(granite_32_file, warp_device, filter, whole_bricks):
    from warptex.texture import SolidTexture

    points = np.random.default_rng(5).uniform(-60.0, 60.0, (20_000, 3))
    cpu = SolidTexture(granite_32_file, seed=4, device="cpu", whole_bricks=whole_bricks)
    # A store too small for one batch's voxels, so that CUDA evicts and rebuilds its table.
    cuda = SolidTexture(granite_32_file, seed=4, device="cuda",
                        cache_bytes=1 << (20 if whole_bricks else 14), whole_bricks=whole_bricks)
    for batch in np.array_split(points, 4):
        np.testing.assert_array_equal(cuda.query(batch, filter=filter),
                                      cpu.query(batch, filter=filter))
    assert cuda.store.stats()["bricks_evicted"] > 0


def test_surface_shell_and_texel_points_agree(warp_device):
    from warptex.bake import texel_points
    from warptex.surface import block_transform, shell

    mesh = trimesh.creation.icosphere(subdivisions=3)
    np.testing.assert_array_equal(shell(mesh, 96, device="cuda"), shell(mesh, 96, device="cpu"))
    uv = np.random.default_rng(2).uniform(0.0, 1.0, (len(mesh.vertices), 2))
    transform = block_transform(mesh, 96)
    on_cpu = texel_points(mesh, uv, transform, (64, 64), device="cpu")
    on_cuda = texel_points(mesh, uv, transform, (64, 64), device="cuda")
    for a, b in zip(on_cpu, on_cuda, strict=True):
        np.testing.assert_array_equal(a, b)


def test_gpu_memory_pools_keep_memory_between_requests(warp_device):
    """CUDA's default pool gives its memory back at every synchronization, which the engine
    makes at every level; warptex raises its release threshold where it was left at 0."""
    import warp as wp

    from warptex.warp_runtime import init_warp

    init_warp()
    pooled = [gpu for gpu in wp.get_cuda_devices() if gpu.is_mempool_enabled]
    assert all(wp.get_mempool_release_threshold(gpu) > 0 for gpu in pooled)


def test_compare_reads_the_device_memory_the_engine_held(warp_device):
    """`compare` reports the high-water mark of Warp's CUDA memory pool for a lazy method on
    a GPU: at least what the process allocated there; nothing for the CPU."""
    import warp as wp

    from warptex.compare import measure

    held = wp.zeros(64 << 20, dtype=wp.uint8, device="cuda:0")
    peak = measure._device_peak_mib("cuda:0")
    assert peak is None or peak >= 64  # None: a device without a memory pool
    assert measure._device_peak_mib("cpu") is None
    del held
