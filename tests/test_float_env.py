"""warptex's work in IEEE arithmetic whatever the calling thread's floating-point mode
(warptex.float_env): Mitsuba's threads read denormals as zero, under which SciPy's k-d
tree recursed without end on some exemplars and the process died of a segmentation fault."""

from __future__ import annotations

import ast
import ctypes
import os
import platform
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from warptex.float_env import ieee_arithmetic

REPO = Path(__file__).resolve().parents[1]
ON_GLIBC_X86_64 = sys.platform.startswith("linux") and platform.machine() == "x86_64"
needs_mxcsr = pytest.mark.skipif(not ON_GLIBC_X86_64,
                                 reason="sets the x86-64 MXCSR through glibc's fenv_t")

# What a test's process runs first to compute as Mitsuba's threads do: glibc's x86-64
# fenv_t holds the SSE control register (MXCSR) at byte 28; 0x8040 sets flush-to-zero and
# denormals-are-zero.
FLUSH_TO_ZERO = textwrap.dedent("""
    import ctypes
    libm = ctypes.CDLL("libm.so.6")
    env = (ctypes.c_uint32 * 64)()
    assert libm.fegetenv(env) == 0
    env[7] |= 0x8040
    assert libm.fesetenv(env) == 0
""")


def _denormal_kept() -> bool:
    return float((np.array([1e-310]) * 1.0)[0]) != 0.0


@needs_mxcsr
def test_the_block_keeps_denormals_and_the_caller_gets_its_mode_back():
    libm = ctypes.CDLL("libm.so.6")
    before = (ctypes.c_uint32 * 64)()
    assert libm.fegetenv(before) == 0
    try:
        exec(FLUSH_TO_ZERO, {})
        assert not _denormal_kept()
        with ieee_arithmetic():
            assert _denormal_kept()
            with ieee_arithmetic():  # nested: the outer block's mode comes back
                pass
            assert _denormal_kept()
        assert not _denormal_kept()
    finally:
        libm.fesetenv(before)
    assert _denormal_kept()


@needs_mxcsr
def test_k_d_trees_are_built_and_searched_alike_under_flush_to_zero(tmp_path):
    """Rows on which SciPy's tree, built with median splits in a thread that reads
    denormals as zero, recursed without end (a segmentation fault: in a process of its
    own); the neighbours found there are those found here."""
    from warptex.parallel import kd_tree, nearest

    rows = REPO / "tests" / "data" / "flush_to_zero_rows.npy"
    # And points a denormal apart, whose distances the mode would read as zero.
    faint = tmp_path / "faint_rows.npy"
    np.save(faint, np.random.default_rng(5).random((300, 3)) * 1e-310)
    script = FLUSH_TO_ZERO + textwrap.dedent(f"""
        import numpy as np
        from warptex.parallel import kd_tree, nearest
        for path in ({str(rows)!r}, {str(faint)!r}):
            rows = np.load(path).astype(np.float64)
            print(nearest(kd_tree(rows), rows[::7], k=4)[1].tolist())
    """)
    done = _run(script, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    for path, seen in zip((rows, faint), done.stdout.splitlines()[-2:], strict=True):
        here = np.load(path).astype(np.float64)
        assert seen == str(nearest(kd_tree(here), here[::7], k=4)[1].tolist()), path.name


def _run(script: str, tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, WARPTEX_CACHE=str(tmp_path / "cache"))
    return subprocess.run([sys.executable, "-c", script, *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)


def _gapped_exemplar(tmp_path: Path) -> Path:
    """Values whose windows made SciPy's tree recurse without end under denormals-are-zero
    (found with a medium's extinction of gaps: rows of one value in noise)."""
    values = np.random.default_rng(0).uniform(0.5, 3.0, (32, 32, 3)).astype(np.float32)
    values[:4] = 0.5
    path = tmp_path / "gaps.npy"
    np.save(path, values)
    return path


def _faint_exemplar(tmp_path: Path) -> Path:
    """Values below float32's smallest normal number, which denormals-are-zero reads as 0
    (the candidates of a flat exemplar)."""
    values = np.random.default_rng(1).uniform(0, 1, (32, 32, 3)).astype(np.float32)
    path = tmp_path / "faint.npy"
    np.save(path, values * np.float32(1e-38))
    return path


@needs_mxcsr
@pytest.mark.parametrize("exemplar", [_gapped_exemplar, _faint_exemplar])
def test_candidates_computed_under_flush_to_zero_are_the_same(tmp_path, exemplar):
    """The caller's mode changes neither whether the pre-computation ends nor what it
    gives (in a process of its own: the failure was a segmentation fault)."""
    from warptex.candidates import precompute

    path = exemplar(tmp_path)
    script = FLUSH_TO_ZERO + textwrap.dedent(f"""
        import numpy as np
        from warptex.candidates import precompute
        assert float((np.array([1e-310]) * 1.0)[0]) == 0.0
        print(precompute({str(path)!r}, cache=False).content_digest)
    """)
    done = _run(script, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-1] == precompute(path, cache=False).content_digest


@needs_mxcsr
@pytest.mark.parametrize("filter", ["trilinear", "nearest"])
def test_points_queried_under_flush_to_zero_get_the_same_colors(tmp_path, filter):
    """Faint colours, below float32's normal numbers, looked up by a thread that flushes
    them (a renderer's) are those any other thread gets."""
    from warptex.candidates import precompute
    from warptex.texture import SolidTexture

    path = _faint_exemplar(tmp_path)
    points = np.random.default_rng(2).uniform(-20, 20, (300, 3))
    np.save(tmp_path / "points.npy", points)
    script = textwrap.dedent(f"""
        import numpy as np
        from warptex.candidates import precompute
        from warptex.texture import SolidTexture
        texture = SolidTexture(precompute({str(path)!r}, cache=False), seed=4)
        points = np.load({str(tmp_path / "points.npy")!r})
    """) + FLUSH_TO_ZERO + textwrap.dedent(f"""
        colors = texture.query(points, filter={filter!r})
        print(colors.astype(np.float32).tobytes().hex())
    """)
    done = _run(script, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    here = SolidTexture(precompute(path, cache=False), seed=4).query(points, filter=filter)
    assert (here != 0).all()
    assert done.stdout.split()[-1] == here.astype(np.float32).tobytes().hex()


@needs_mxcsr
def test_a_texture_loaded_under_flush_to_zero_is_the_same(tmp_path):
    """The plugin's texture, made on a thread that flushes denormals (Mitsuba's), has the
    colour range and mean of one made on any other."""
    script = textwrap.dedent(f"""
        import sys
        import mitsuba as mi
        mi.set_variant("scalar_rgb")
        import mitsuba_plugin
        mitsuba_plugin.register()
        if sys.argv[1:] == ["flushed"]:
            exec({FLUSH_TO_ZERO!r})
        texture = mi.load_dict({{"type": "lazy_solid",
                                "exemplar": {str(_faint_exemplar(tmp_path))!r}}})
        print(repr((texture.lowest, texture.largest, float(texture.mean()))))
    """)
    seen = [_run(script, tmp_path, *mode) for mode in ([], ["flushed"])]
    assert [s.returncode for s in seen] == [0, 0], seen[1].stderr[-2000:]
    plain, flushed = (s.stdout.splitlines()[-1] for s in seen)
    assert ast.literal_eval(plain)[1] > 0 and flushed == plain


def test_a_medium_of_lazy_solids_loads_on_mitsubas_threads(tmp_path):
    """Mitsuba builds the textures nested in a medium on its own threads, which flush
    denormals: the candidates of the extinction's exemplar are computed there."""
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    script = textwrap.dedent(f"""
        import mitsuba as mi
        import warptex
        mi.set_variant("scalar_rgb")
        import mitsuba_plugin
        mitsuba_plugin.register()
        medium = mi.load_dict({{"type": "lazy_solid_medium",
                               "albedo": {{"type": "lazy_solid", "exemplar": {str(wood)!r}}},
                               "sigma_t": {{"type": "lazy_solid",
                                           "exemplar": {str(_gapped_exemplar(tmp_path))!r}}}}})
        print("loaded", medium is not None)
    """)
    done = _run(script, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-2:] == ["loaded", "True"]
