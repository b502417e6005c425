"""Shared fixtures. Tests run Warp on the CPU (and on a GPU where the machine has one:
see ``warp_device``) with a project-local kernel cache."""

from __future__ import annotations

import errno
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent

# Before anything imports Warp, so compiled kernels land in one known, reusable folder.
if not os.environ.get("WARP_CACHE_PATH"):  # an empty one is unset (warptex.warp_runtime)
    os.environ["WARP_CACHE_PATH"] = str(REPO / ".cache" / "warp")
# The candidates the tests pre-compute stay in the checkout, not among the user's own
# (where every change of the code would leave another set); tests of the cache set theirs.
os.environ["WARPTEX_CACHE"] = str(REPO / ".cache" / "candidates")

import warp as wp  # noqa: E402

# Every array of a launch on the launch's device, as Warp had it before its relaxed default:
# on a GPU machine a host array in a CUDA launch then raises, where it would be read across
# the bus or crash. On the CPU alone, every array is there.
wp.config.launch_array_access_mode = wp.config.LaunchArrayAccessMode.STRICT

# A shell without job control starts a background job with Ctrl-C ignored, and Python then
# raises no KeyboardInterrupt, nor do the commands the tests start (they inherit the
# ignoring): the tests of what Ctrl-C does would fail or wait for nothing. Python's own
# handler restored, children start with the default one.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(autouse=True)
def _memory_read_afresh():
    """The engine reads the process's memory once (``synthesis._host_memory``): a test
    that fakes it (``machine.physical_memory``) must not leave its parts' cap to the next."""
    yield
    from warptex import synthesis

    synthesis._host_memory.cache_clear()


@pytest.fixture(scope="session")
def warp_device() -> str:
    """Warp initialised once per session, with CPU as Warp's default device. warptex's
    own default (``warptex.device()``) is left as it is: a GPU where Warp sees one, so on
    such a machine the engine and store run there unless a test names the device
    (WARPTEX_DEVICE=cpu keeps them on the CPU)."""
    import warp as wp

    from warptex.warp_runtime import init_warp

    init_warp()
    wp.set_device("cpu")
    return "cpu"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """Small test inputs kept in the repository."""
    return REPO / "tests" / "data"


@pytest.fixture(scope="session")
def exemplar_dir() -> Path:
    """The shared exemplar photographs beside the repository (``../shared/data/exemplars``)."""
    path = REPO.parent / "shared" / "data" / "exemplars"
    if not path.is_dir():
        pytest.skip(f"shared exemplars not found at {path}")
    return path


@pytest.fixture(scope="session")
def srgb_decoded():
    """The sRGB transfer function inverted (IEC 61966-2-1), computed apart from Mitsuba:
    the linear colors a render sees of an 8-bit exemplar's values."""
    def decoded(srgb: np.ndarray) -> np.ndarray:
        srgb = np.asarray(srgb, np.float64)
        return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return decoded


@pytest.fixture(scope="module")
def granite_32_file(data_dir, tmp_path_factory):
    """A 32x32 granite crop as a PNG file, with its own candidate cache for the module
    using it, so set-up stays quick."""
    from PIL import Image

    folder = tmp_path_factory.mktemp("granite32")
    path = folder / "granite_32.png"
    Image.open(data_dir / "granite_64.png").crop((0, 0, 32, 32)).save(path)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("WARPTEX_CACHE", str(folder / "cache"))
        yield path


@pytest.fixture(scope="module")
def granite_32(data_dir):
    """The same 32x32 granite crop as an Exemplar held in memory (no file, no cache)."""
    import numpy as np

    from warptex.exemplar import Exemplar

    full = Exemplar.load(data_dir / "granite_64.png")
    return Exemplar(np.ascontiguousarray(full.colors[:32, :32]), name="granite_32")


@pytest.fixture(scope="module")
def granite_32x48(data_dir):
    """A 32-row, 48-column granite crop: pixel indices are row * width + column, and a
    square exemplar would hide a height read for a width."""
    import numpy as np

    from warptex.exemplar import Exemplar

    full = Exemplar.load(data_dir / "granite_64.png")
    return Exemplar(np.ascontiguousarray(full.colors[:32, :48]), name="granite_32x48")


def _plane_scene(texture: dict, emissive: bool, x: float = 0.0, size: int = 8,
                 spp: int = 4):
    """A [-1, 1]^2 plane at z = 0 seen by an orthographic camera centred at (x, 0).

    Emissive: the texture is the plane's radiance, seen directly, so pixels are exact.
    Otherwise it is a diffuse reflectance under a white environment. Built in the Mitsuba
    variant current at the call.
    """
    import mitsuba as mi

    sensor = {
        "type": "orthographic",
        "to_world": mi.ScalarTransform4f().look_at(origin=[x, 0, 5], target=[x, 0, 0],
                                                   up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": spp},
    }
    plane = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([2, 2, 1])}
    if emissive:
        plane |= {"emitter": {"type": "area", "radiance": texture},
                  "bsdf": {"type": "diffuse", "reflectance": 0.0}}
        lights = {}
    else:
        plane["bsdf"] = {"type": "diffuse", "reflectance": texture}
        lights = {"light": {"type": "constant"}}
    return mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                         "sensor": sensor, "plane": plane} | lights)


@pytest.fixture(scope="session")
def plane_scene():
    """A builder of the scene of a textured plane, ``plane_scene(texture, emissive, x=0,
    size=8, spp=4)`` (see ``_plane_scene``)."""
    return _plane_scene


@pytest.fixture
def disk_full_at(monkeypatch):
    """``disk_full_at(path)``: from then on, renaming a finished file to ``path`` fails as on
    a full disk (every output is written under another name, then renamed)."""
    replace = os.replace

    def fill(path: Path) -> None:
        def replace_unless_full(src, dst, *args, **kwargs):
            if Path(dst) == path:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
            return replace(src, dst, *args, **kwargs)

        monkeypatch.setattr(os, "replace", replace_unless_full)

    return fill


@pytest.fixture
def errors_on_a_thread():
    """``errors_on_a_thread(work)``: runs ``work()`` on a thread of its own and returns what
    it raised there, as a list (empty where nothing), for the test's thread to assert on."""
    def run(work) -> list[BaseException]:
        errors: list[BaseException] = []

        def catching() -> None:
            try:
                work()
            except BaseException as error:  # whatever it raises is the failure
                errors.append(error)

        thread = threading.Thread(target=catching)
        thread.start()
        thread.join()
        return errors

    return run
