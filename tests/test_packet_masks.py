"""The packet kernels' tests of a mask's sixteen lanes (drr.cl's ANY16 and ALL16): whichever way
this CPU answers them (AVX-512's mask register, AVX's sign bits, or the built-ins), against
NumPy's any and all, lane by lane (the cast they steer: test_xray_renderer.py)."""

import numpy as np
import pytest

from appliance.xray.device import ClDevice

PROBE = """
kernel void mask_tests(global const int *masks, global int *out)
{
    const int16 m = vload16(get_global_id(0), masks);
    out[2 * get_global_id(0)] = ANY16(m) ? 1 : 0;
    out[2 * get_global_id(0) + 1] = ALL16(m) ? 1 : 0;
}
"""


def masks() -> np.ndarray:
    """Every one-lane and all-but-one-lane mask, none, all, and random ones: -1 on, 0 off (the
    comparisons' results)."""
    rows = [np.zeros(16, bool), np.ones(16, bool)]
    for lane in range(16):
        one = np.zeros(16, bool)
        one[lane] = True
        rows += [one, ~one]
    rows += list(np.random.default_rng(5).random((200, 16)) < 0.5)
    return -np.array(rows, dtype=np.int32)


@pytest.mark.parametrize("options", [[], ["-DNO_MASK_REGISTERS"]])
def test_any_and_all_of_a_packet_mask_are_numpys(options):
    import pyopencl as cl

    dev = ClDevice("cpu")
    m = masks()
    program = cl.Program(dev.ctx, dev.source + PROBE).build(options=["-DUNALIGNED_PAIRS", *options])
    out = dev.scratch(m.shape[0] * 8)
    cl.Kernel(program, "mask_tests")(dev.queue, (m.shape[0],), None, dev.upload(m), out)
    got = dev.download(out, np.empty((m.shape[0], 2), np.int32))
    np.testing.assert_array_equal(got[:, 0], (m != 0).any(axis=1))
    np.testing.assert_array_equal(got[:, 1], (m != 0).all(axis=1))
