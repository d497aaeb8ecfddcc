"""Whether an OpenCL device can build drr.cl and make its kernels: run as a script of its own.

`python build_probe.py P:D [P:D ...]` tries, in order, device D of platform P (indices in
pyopencl's listing, which a child with the parent's environment lists the same way). Each try
prints one JSON line, {"device": "P:D", "why": null or the reason}, and the script stops at
the first device that works. It ends with os._exit, releasing nothing.

Why a process of its own: a compiler can fail in ways that take the process with it. The
PoCL 3.0 that pyopencl's wheel carries (LLVM 14) builds drr.cl on an AMD Zen 4 with no
error, yet makes none of its kernels (of some sources only when the build is read back from
its kernel cache), and releasing that build's context aborts the process ("still have
references to IRs"). A device whose probe dies that way has no line; the parent names it
from the exit status and tries the next in a new probe.

This file imports pyopencl only, so the parent's `device.py` can take `build_options` from it.
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

SOURCE = Path(__file__).with_name("drr.cl")
_KERNEL_NAMES = re.compile(r"^kernel void (\w+)\(", re.MULTILINE)
#: Every program this process built, never released (see above).
_kept: list = []


def build_options(is_cpu: bool) -> list[str]:
    """drr.cl's build options: a CPU device reads its packed pairs of samples unaligned."""
    return ["-DUNALIGNED_PAIRS"] if is_cpu else []


def kernel_names(source: str) -> list[str]:
    return _KERNEL_NAMES.findall(source)


def first_error(text: str) -> str:
    """A failed build's cause: its compiler's first "error:" line (the rest follow from it)."""
    lines = [ln.strip() for ln in text.splitlines() if "error:" in ln]
    return lines[0] if lines else (text.strip().splitlines() or ["no build log"])[0]


def cannot_build(d, source: str) -> str | None:
    """Why device `d` cannot build `source` and make each of its kernels, or None if it can:
    built twice, since the renderer's build is the second (PoCL's kernel cache has the probe's),
    and the wheel's PoCL 3.0 on a Zen 4 makes every kernel of a fresh build of drr.cl and none
    of the same build read back from its cache."""
    import pyopencl as cl

    for again in (False, True):
        program = cl.Program(cl.Context([d]), source)
        _kept.append(program)
        try:
            program.build(options=build_options(bool(d.type & cl.device_type.CPU)))
        except cl.Error as e:
            return first_error(str(e))
        for name in kernel_names(source):
            try:
                cl.Kernel(program, name)
            except cl.Error as e:
                built = " built again from its kernel cache" if again else ""
                return f"drr.cl builds but its compiler made no kernel {name}{built} ({e})"
    return None


def main(argv: list[str]) -> None:
    import warnings

    import pyopencl as cl

    warnings.simplefilter("ignore")                     # the compiler's warnings are not the answer
    source = SOURCE.read_text()
    platforms = cl.get_platforms()
    for spec in argv:
        p, d = (int(i) for i in spec.split(":"))
        why = cannot_build(platforms[p].get_devices()[d], source)
        print(json.dumps({"device": spec, "why": why}), flush=True)
        if why is None:
            break
    os._exit(0)                                         # each line was flushed as printed


if __name__ == "__main__":
    main(sys.argv[1:])
