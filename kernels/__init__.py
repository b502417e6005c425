"""NVIDIA Warp kernels and ``@wp.func`` helpers used by warptex; no host-side logic lives here."""
