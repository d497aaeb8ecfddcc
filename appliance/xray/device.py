"""The OpenCL device and the programs built on it: one context, one queue, one lock.

Picking the device, compiling drr.cl (and its blended variant on first use) and handing
out kernels and buffers is all this module does; the casting and the detector model ask it
for what they need.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

from ..errors import FluorosimError
from . import build_probe

log = logging.getLogger(__name__)


def pick_device(device: str):
    """An OpenCL device: "auto" prefers a GPU and falls back to PoCL's CPU device; "cpu" PoCL only.

    Of several, the first whose compiler can build for this machine.
    """
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    gpus, cpus, seen = [], [], set()
    for p in platforms:
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        for d in devs:
            if d.int_ptr in seen:       # a loader that reads one vendor file twice lists its platform twice
                continue
            seen.add(d.int_ptr)
            if d.type & cl.device_type.GPU:
                gpus.append(d)
            elif d.type & cl.device_type.CPU:
                cpus.append(d)
    if device not in ("auto", "cpu", "gpu"):
        raise FluorosimError(f"OpenCL device '{device}' is not one of auto, cpu, gpu")
    choice = (gpus if device == "gpu" else cpus if device == "cpu" else gpus + cpus)
    if not choice:
        _refuse_for_the_cache()
        raise FluorosimError(f"no OpenCL {'device' if device == 'auto' else device + ' device'} found; "
                             "install PoCL (pip install 'pyopencl[pocl]') or the GPU's OpenCL driver")
    refusals: list[str] = []
    with _probe_lock:                       # two renderers made at once probe once
        for d, why in _probed(choice, platforms):
            if why is None:
                for refusal in refusals:    # a service technician sees why a device was passed over, once
                    if refusal not in _logged:
                        _logged.add(refusal)
                        log.warning("OpenCL device skipped, it cannot compile the renderer's kernels: %s", refusal)
                return d
            refusals.append(f"{d.name.strip()} ({d.platform.version.strip()}): {why}")
    _refuse_for_the_cache()
    raise FluorosimError("no OpenCL device here can compile kernels for this machine ("
                         + "; ".join(refusals) + "); install Debian's pocl-opencl-icd (make setup does) "
                         "or a PoCL whose LLVM knows this processor")


def pocl_cache_dir() -> Path:
    """Where PoCL keeps the kernels it compiled (its own rule: POCL_CACHE_DIR, else the XDG cache)."""
    if os.environ.get("POCL_CACHE_DIR"):
        return Path(os.environ["POCL_CACHE_DIR"])
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "pocl" / "kcache"


def _refuse_for_the_cache() -> None:
    """Refuse naming PoCL's kernel cache where it cannot be written (a full disk, a file in the
    way): PoCL then lists no device or fails every build, and the refusal's usual advice, to
    install another OpenCL, would send the technician the wrong way."""
    folder = pocl_cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder) as f:
            f.write(bytes(64 * 1024))          # a compiled kernel's size, written through
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        raise FluorosimError(f"no OpenCL device can compile kernels: PoCL's kernel cache {folder} cannot be written "
                             f"({e.strerror or e}); free space there, or set POCL_CACHE_DIR to a writable folder") from None


#: Each device's probe answer this process has had, by the device's handle: None where it
#: builds drr.cl and makes its kernels, else why not.
_probe_answers: dict[int, str | None] = {}
_probe_lock = threading.Lock()
#: The devices passed over that this process has logged (their refusals).
_logged: set[str] = set()
_PROBE_TIMEOUT_S = 600.0


def _probed(devices: list, platforms: list):
    """(device, why) for `devices` in order up to the first that builds (why None), each asked
    of a build_probe process once a process.

    A PoCL is built against one LLVM, which names the host processor for code generation; on a
    processor newer than that LLVM it may refuse every build ('generic' on an AMD family 1Ah
    EPYC) or, worse, build drr.cl and make none of its kernels (LLVM 14 on Zen 4), and then
    abort the process when the build is released. So the builds are tried in a process of
    their own; another PoCL on the same machine (Debian's picks a kernel-library target by the
    processor's features) may build fine, and its kernels come from the compiler's cache when
    the renderer builds them here.
    """
    for d in devices:
        if d.int_ptr not in _probe_answers:
            _ask_probe([e for e in devices if e.int_ptr not in _probe_answers], platforms)
        why = _probe_answers[d.int_ptr]
        yield d, why
        if why is None:
            return


def _ask_probe(devices: list, platforms: list) -> None:
    """Run one build_probe over `devices`: its lines answer those it tried; the first without a
    line, where the probe died, is answered with how it died. The rest wait for the next."""
    specs = {f"{platforms.index(d.platform)}:{d.platform.get_devices().index(d)}": d for d in devices}
    try:
        out = subprocess.run([sys.executable, str(build_probe.__file__), *specs], capture_output=True,
                             stdin=subprocess.DEVNULL, text=True, timeout=_PROBE_TIMEOUT_S)
        answers = [a for a in map(_answer, out.stdout.splitlines()) if a is not None and a["device"] in specs]
        said = (out.stderr.strip().splitlines() or [""])[-1]
        died = (f"its compiler killed the probe process ({_exit_status(out.returncode)}{': ' + said if said else ''})"
                if out.returncode else "the probe process ended before trying it")
    except subprocess.TimeoutExpired:
        answers, died = [], f"its compiler did not finish drr.cl within {_PROBE_TIMEOUT_S:.0f} s"
    for answer in answers:
        _probe_answers[specs[answer["device"]].int_ptr] = answer["why"]
    untried = [d for d in devices if d.int_ptr not in _probe_answers]
    if untried and all(answer["why"] is not None for answer in answers):
        _probe_answers[untried[0].int_ptr] = died


def _answer(line: str) -> dict | None:
    """A build_probe line, or None for anything else a driver may print on its standard output."""
    try:
        answer = json.loads(line)
    except ValueError:
        return None
    return answer if isinstance(answer, dict) and isinstance(answer.get("device"), str) else None


def _exit_status(returncode: int) -> str:
    if returncode < 0:
        try:
            return signal.Signals(-returncode).name
        except ValueError:
            pass
    return f"exit status {returncode}"


def is_cpu_device(device) -> bool:
    """Whether the OpenCL `device` is a CPU's (PoCL)."""
    import pyopencl as cl
    return bool(device.type & cl.device_type.CPU)


#: drr.cl's builds beside the plain one, by the macro that makes each: BLEND mixes two phases in
#: the cast (a moving frame between two phases), SPLIT casts two phases in one pass, each into
#: its own integrals (the projection cache's pair); SLABBED reads each packet of a moving frame from
#: the slab copy where its rays allow, else from the full volume (slabs.py), alone or with either.
VARIANTS = ("BLEND", "SPLIT", "SLABBED", "SLABBED BLEND", "SLABBED SPLIT")


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
        self.is_cpu = is_cpu_device(self.device)
        self.source = build_probe.SOURCE.read_text()
        self.options = build_probe.build_options(self.is_cpu)
        self.program = cl.Program(self.ctx, self.source).build(options=self.options)
        self._variants: dict[str, cl.Program] = {}
        self._variants_lock = threading.Lock()
        self.lock = threading.Lock()

    def kernel(self, name: str, variant: str | None = None):
        """Kernel `name` of drr.cl, a new one per call (its arguments are the caller's); with
        `variant`, of that build (VARIANTS), made once per device for every caller: each of a
        renderer's matrices asks for them, and a build takes 40-60 ms even from PoCL's cache."""
        if variant is None:
            return self.cl.Kernel(self.program, name)
        if variant not in VARIANTS:
            raise ValueError(f"drr.cl has no build {variant!r}; its builds are {', '.join(VARIANTS)}")
        with self._variants_lock:
            if variant not in self._variants:
                self._variants[variant] = self.cl.Program(self.ctx, self.source).build(
                    options=[*(f"-D{m}" for m in variant.split()), *self.options])
            return self.cl.Kernel(self._variants[variant], name)

    def upload(self, host: np.ndarray, writable: bool = False):
        """A device buffer holding a copy of `host`."""
        mf = self.cl.mem_flags
        return self.cl.Buffer(self.ctx, (mf.READ_WRITE if writable else mf.READ_ONLY) | mf.COPY_HOST_PTR, hostbuf=host)

    def scratch(self, nbytes: int):
        return self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, nbytes)

    def download(self, buffer, out: np.ndarray) -> np.ndarray:
        self.cl.enqueue_copy(self.queue, out, buffer)
        return out
