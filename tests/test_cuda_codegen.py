"""Every Warp kernel of ``kernels/`` also compiles for CUDA.

No GPU has been lent to this project's test machines, so the CUDA code of the kernels would
otherwise never be built here; Warp's bundled NVRTC compiles it to PTX without a driver.
Running that code needs a GPU: ``test_synthesis.py::test_cpu_and_cuda_agree_bit_for_bit``.
"""

from __future__ import annotations

import importlib
import pkgutil
import re

import pytest
import warp as wp

import kernels

MODULES = [f"kernels.{m.name}" for m in pkgutil.iter_modules(kernels.__path__)]
# Those whose colours the CPU and a GPU must give to the bit (the brick store's lookups,
# baked textures and surface points): no fused multiply-add, every float operation rounded
# to nearest rather than left to ptxas to contract.
EXACT_FLOATS = ("kernels.bake", "kernels.lookup", "kernels.surface")


def _cuda_arch() -> int:
    archs = wp.get_cuda_supported_archs()
    if not archs:
        pytest.skip("this Warp build has no CUDA compiler")
    return archs[0]  # the oldest target: PTX for it runs on every newer GPU


@pytest.mark.parametrize("name", MODULES)
def test_kernels_compile_for_cuda(name, warp_device):
    module = importlib.import_module(name)
    module_kernels = [k for k in vars(module).values() if isinstance(k, wp.Kernel)]
    if not module_kernels:
        pytest.skip(f"{name} holds only functions, built into the modules that call them")
    files = wp.compile_aot_module(module, arch=_cuda_arch(), use_ptx=True)
    ptx = "".join(p.read_text() for p in files)
    entries = re.findall(r"\.entry\s+(\w+)\(", ptx)
    if name in EXACT_FLOATS:
        assert "fma" not in ptx, f"{name}: fused multiply-adds in its PTX"
        unrounded = re.findall(r"^\s*(?:add|sub|mul)\.f(?:32|64)\b.*$", ptx, re.MULTILINE)
        assert not unrounded, f"{name}: float arithmetic without .rn: {unrounded[0].strip()}"
    for kernel in module_kernels:
        # One forward entry per overload: a generic kernel compiles only those declared.
        count = max(1, len(kernel.overloads)) if kernel.is_generic else 1
        found = [e for e in entries if e.startswith(f"{kernel.key}_")]
        assert len(found) == count, f"{name}.{kernel.key}: {len(found)} CUDA entries"
