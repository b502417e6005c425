"""NVIDIA Warp kernels and ``@wp.func`` helpers used by warptex; no host-side logic lives here."""

# Tells this package from others named ``kernels`` that would hide it (warptex/__init__.py).
WARPTEX_KERNELS = True
