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
    entries = re.findall(r"\.entry\s+(\w+)\(", "".join(p.read_text() for p in files))
    for kernel in module_kernels:
        # One forward entry per overload: a generic kernel compiles only those declared.
        count = max(1, len(kernel.overloads)) if kernel.is_generic else 1
        found = [e for e in entries if e.startswith(f"{kernel.key}_")]
        assert len(found) == count, f"{name}.{kernel.key}: {len(found)} CUDA entries"
