"""warptex: lazy, deterministic solid texture synthesis from 2D exemplars with NVIDIA Warp.

Implements Dong et al. 2008, "Lazy Solid Texture Synthesis". ``precompute``, ``CandidateSet``
(§4, 3D candidates), ``Synthesizer`` (§5, parallel synthesis of any voxel subset) and
``SolidTexture`` (§5.2, point queries on a cached brick store) are imported on first use:
``import warptex`` loads Warp, NumPy and SciPy (exemplars are read with them) but none of
the synthesis code, nor Mitsuba or trimesh.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from typing import Any

from warptex.stops import quiet_while_starting

quiet_while_starting()  # before the heavy imports below and the command's own

# Before anything can import Mitsuba: Dr.Jit reads DRJIT_LIBLLVM_PATH when its backend starts.
from warptex.llvm import best_mitsuba_variant, configure_drjit  # noqa: E402

configure_drjit()


def _check_kernels_package() -> None:
    """Refuse, in one message, a ``kernels`` package that is not warptex's: PyPI's package
    of that name installed over it, or a ``kernels`` package first on the path, would fail
    later with an error naming neither. (A folder named ``kernels`` without an
    ``__init__.py`` or a module named as one of warptex's, a cache say, only joins
    warptex's modules to it.)"""
    try:
        from kernels import common
    except ImportError as error:
        _check_dependency(error)
        why = str(error)
    else:
        # An editable install's import hook serves warptex's modules by name to a package
        # that lacks them, so common may be warptex's and the package's others not.
        home = Path(common.__file__).resolve().parent
        # Other files: an install of links to warptex's own (a strict editable one) hides
        # nothing.
        hiding = [other for folder in sys.modules["kernels"].__path__
                  for mine in sorted(home.glob("*.py"))
                  if (other := Path(folder) / mine.name).exists()
                  and other.resolve() != mine.resolve()]
        if not getattr(common, "WARPTEX_KERNELS", False):
            why = f"{common.__file__} is not warptex's"
        elif hiding:
            why = f"its {hiding[0]} hides warptex's {home / hiding[0].name}"
        else:
            return
    package = sys.modules.get("kernels")
    found = getattr(package, "__file__", None) or list(getattr(package, "__path__", []))
    raise ImportError(f"warptex's Warp kernels are the top-level package 'kernels', and the "
                      f"one Python found, {found}, is another ({why}): PyPI's 'kernels' "
                      "package installed in this environment, or a 'kernels' package in the "
                      "working folder or on PYTHONPATH. Give warptex an environment of its "
                      "own, or run it from another folder.")


def _check_dependency(error: ImportError) -> None:
    """Refuse, in one message, a Python without warptex's dependencies (Warp, NumPy): the
    system's ``python3`` where the checkout's ``.venv`` was meant, whose failure to import
    warptex's own kernels is not another ``kernels`` package."""
    missing = error.name if isinstance(error, ModuleNotFoundError) else None
    if missing is None or missing.partition(".")[0] == "kernels":
        return
    spec = importlib.util.find_spec("kernels")
    folders = [] if spec is None else spec.submodule_search_locations or []
    found = [Path(folder).resolve() for folder in folders]
    if Path(__file__).resolve().parent.parent / "kernels" not in found:
        return
    raise ImportError(f"warptex needs the module '{missing}', which this Python "
                      f"({sys.executable}) does not have: run warptex in the environment it "
                      "was installed in (`. .venv/bin/activate` in the checkout, after `make "
                      "demo`), or install it here with its dependencies (`pip install .` in "
                      "the checkout)") from None


_check_kernels_package()

from warptex.exemplar import Exemplar, ExemplarError, PyramidLevel  # noqa: E402
from warptex.warp_runtime import device  # noqa: E402

__version__ = "0.1.0"

_LAZY = {
    "precompute": "warptex.candidates",
    "CandidateSet": "warptex.candidate_set",
    "Synthesizer": "warptex.synthesis",
    "SolidTexture": "warptex.texture",
    "SettingError": "warptex.settings",
    "StoreFileError": "warptex.store_files",
}
# Submodules the README names as ``warptex.<module>.<name>``, imported on first access too.
_SUBMODULES = ("bake", "baselines", "candidates", "compare", "cut", "dependencies",
               "mesh_files", "metrics", "sheets", "srgb", "store", "store_files", "surface",
               "synthesis", "texture", "volume_files")

__all__ = [
    "CandidateSet",
    "Exemplar",
    "ExemplarError",
    "PyramidLevel",
    "SettingError",
    "SolidTexture",
    "StoreFileError",
    "Synthesizer",
    "__version__",
    "best_mitsuba_variant",
    "device",
    "precompute",
]


def __getattr__(name: str) -> Any:
    """Import the heavier synthesis modules on first access (PEP 562)."""
    if name in _SUBMODULES:
        return importlib.import_module(f"warptex.{name}")
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'warptex' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public names and the submodules README names: what completion offers (the
    helpers this module imports, such as ``sys``, are not warptex's API)."""
    return sorted(set(__all__) | set(_SUBMODULES))
