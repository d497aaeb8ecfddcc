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
    """An OpenCL device: "auto" prefers a GPU and falls back to PoCL's CPU device; "cpu" PoCL only.

    Of several, the first whose compiler can build for this machine.
    """
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
    refusals = []
    for d in choice:
        why = _cannot_compile(d)
        if why is None:
            return d
        refusals.append(f"{d.name.strip()} ({d.platform.version.strip()}): {why}")
    raise FluorosimError("no OpenCL device here can compile kernels for this machine ("
                         + "; ".join(refusals) + "); install Debian's pocl-opencl-icd (make setup does) "
                         "or a PoCL whose LLVM knows this processor")


_PROBE_KERNEL = "__kernel void probe(__global float *a) { a[get_global_id(0)] *= 2.0f; }"
_compile_checked: dict[int, str | None] = {}


def _cannot_compile(d) -> str | None:
    """Why device `d` cannot build a kernel, or None if it can.

    A PoCL is built against one LLVM, which names the host processor for code generation; on a
    processor newer than that LLVM (PoCL 3.0's LLVM 14 on an AMD family 1Ah EPYC, say) it
    names it 'generic', which LLVM's x86 back end refuses, so every build fails. Another PoCL
    on the same machine (Debian's picks a kernel-library target by the processor's features)
    may build fine: the first device that builds a trivial kernel is the one used.
    """
    import pyopencl as cl

    key = d.int_ptr
    if key not in _compile_checked:
        try:
            cl.Program(cl.Context([d]), _PROBE_KERNEL).build()
            _compile_checked[key] = None
        except cl.Error as e:
            lines = [ln.strip() for ln in str(e).splitlines() if "error:" in ln]
            _compile_checked[key] = lines[0] if lines else str(e).splitlines()[0]
    return _compile_checked[key]


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
