"""Splitting one Warp launch over CPU threads gives the result of one launch."""

from typing import Any

import numpy as np
import warp as wp

from warptex.parallel import MIN_SPLIT, launch_ranges


@wp.kernel
def _double(first: int, a: wp.array(dtype=Any), out: wp.array(dtype=wp.float32)):
    i = first + wp.tid() // 2
    if wp.tid() % 2 == 0:
        out[i] = wp.float32(a[i]) * 2.0


def test_split_generic_launch_equals_one_launch(warp_device):
    n = 4 * MIN_SPLIT + 3
    values = np.arange(n) % 251
    for dtype in (wp.uint16, wp.int32):  # each dtype is a new overload, built on first use
        a = wp.array(values, dtype=dtype, device="cpu")
        out = wp.full(n, -1.0, dtype=wp.float32, device="cpu")
        launch_ranges(_double, 5, n, [a], [out], per_item=2)
        expected = np.where(np.arange(n) >= 5, 2.0 * values, -1.0)
        assert np.array_equal(out.numpy(), expected.astype(np.float32))
