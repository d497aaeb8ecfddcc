"""The OpenCL device and the programs built on it: one context, one queue, one lock.

Picking the device, compiling drr.cl (and its blended variant on first use) and handing
out kernels and buffers is all this module does; the casting and the detector model ask it
for what they need.
"""

from __future__ import annotations

import threading
from importlib import resources

import numpy as np

from ..errors import FluorosimError


def pick_device(device: str):
    """An OpenCL device: "auto" prefers a GPU and falls back to PoCL's CPU device; "cpu" PoCL only."""
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    gpus, cpus = [], []
    for p in platforms:
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        for d in devs:
            if d.type & cl.device_type.GPU:
                gpus.append(d)
            elif d.type & cl.device_type.CPU:
                cpus.append(d)
    if device not in ("auto", "cpu", "gpu"):
        raise FluorosimError(f"OpenCL device '{device}' is not one of auto, cpu, gpu")
    choice = (gpus if device == "gpu" else cpus if device == "cpu" else gpus + cpus)
    if not choice:
        raise FluorosimError(f"no OpenCL {'device' if device == 'auto' else device + ' device'} found; "
                             "install PoCL (pip install 'pyopencl[pocl]') or the GPU's OpenCL driver")
    return choice[0]


class ClDevice:
    """One OpenCL device with drr.cl built on it.

    `lock` keeps one frame at a time on the queue; `is_cpu` picks the vectorised packet kernels.
    """

    def __init__(self, device: str = "auto"):
        import pyopencl as cl

        self.cl = cl
        self.device = pick_device(device)
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.ctx)
        self.is_cpu = bool(self.device.type & cl.device_type.CPU)
        self.source = resources.files("appliance.xray").joinpath("drr.cl").read_text()
        self.options = ["-DUNALIGNED_PAIRS"] if self.is_cpu else []
        self.program = cl.Program(self.ctx, self.source).build(options=self.options)
        self._blend_program: cl.Program | None = None
        self.lock = threading.Lock()

    def kernel(self, name: str, blend: bool = False):
        """Kernel `name` of drr.cl; with `blend`, of the build that mixes two phases."""
        if not blend:
            return self.cl.Kernel(self.program, name)
        if self._blend_program is None:
            self._blend_program = self.cl.Program(self.ctx, self.source).build(options=["-DBLEND", *self.options])
        return self.cl.Kernel(self._blend_program, name)

    def upload(self, host: np.ndarray, writable: bool = False):
        """A device buffer holding a copy of `host`."""
        mf = self.cl.mem_flags
        return self.cl.Buffer(self.ctx, (mf.READ_WRITE if writable else mf.READ_ONLY) | mf.COPY_HOST_PTR, hostbuf=host)

    def scratch(self, nbytes: int):
        return self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, nbytes)

    def download(self, buffer, out: np.ndarray) -> np.ndarray:
        self.cl.enqueue_copy(self.queue, out, buffer)
        return out
