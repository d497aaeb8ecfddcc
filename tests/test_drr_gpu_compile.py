"""drr.cl as a GPU's OpenCL compiler sees it, without a GPU: Clang (Debian's, which PoCL
installs) compiles it as OpenCL C 1.2 for an NVIDIA target (PTX) and an AMD one (GCN), with
the GPU's build options (appliance/xray/build_probe.py: none) and with the blended variant.

The CPU's kernels are built here by PoCL on every test run; the GPU's path (joseph_materials,
the per-pixel polychromatic and noise kernels, no AVX-512 builtins, no unaligned pairs) is
otherwise compiled only on a machine with a GPU. Ground truth: the compiler's own verdict, and
each kernel the source declares present as an entry point in the code it emits.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from appliance.xray.build_probe import build_options

REPO = Path(__file__).resolve().parents[1]
DRR_CL = REPO / "appliance" / "xray" / "drr.cl"
CLANG = shutil.which("clang-15") or shutil.which("clang")
needs_clang = pytest.mark.skipif(CLANG is None, reason="clang is not installed (Debian package clang-15, which "
                                                        "pocl-opencl-icd brings; make setup installs it)")

#: target triple, extra flags, and how the emitted code names a kernel's entry point.
TARGETS = {
    "NVIDIA (PTX)": ("nvptx64-nvidia-nvcl", [], r"\.entry (\w+)\("),
    "AMD (GCN)": ("amdgcn-amd-amdhsa", ["-mcpu=gfx90a", "-nogpulib"], r"\.amdhsa_kernel (\w+)"),
}


def _compiled(tmp_path, source: Path, target: str, options: list[str]) -> tuple[set[str], set[str]]:
    """(kernels `source` declares, entry points of what Clang emits for `target`), asserting it compiled cleanly."""
    triple, extra, entry = TARGETS[target]
    out = tmp_path / f"{source.stem}.s"
    done = subprocess.run([CLANG, "-x", "cl", "-cl-std=CL1.2", "-target", triple, *extra,
                           "-Xclang", "-finclude-default-header", "-O2", "-S", *options, "-o", str(out), str(source)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "error:" not in done.stderr
    declared = set(re.findall(r"^kernel void (\w+)\(", source.read_text(), re.MULTILINE))
    return declared, set(re.findall(entry, out.read_text()))


@needs_clang
@pytest.mark.parametrize("target", sorted(TARGETS))
@pytest.mark.parametrize("blend", [False, True])
def test_drr_cl_compiles_for_a_gpu_with_every_kernel(tmp_path, target, blend):
    options = build_options(is_cpu=False) + (["-DBLEND"] if blend else [])
    declared, emitted = _compiled(tmp_path, DRR_CL, target, options)
    assert len(declared) >= 6
    assert emitted == declared


@needs_clang
@pytest.mark.parametrize("target", sorted(TARGETS))
def test_the_detector_chain_compiles_for_a_gpu_with_every_kernel(tmp_path, target):
    """detector_chain.cl runs only on GPUs (device_chain.py), so only its PoCL build is run here."""
    from appliance.xray.device_chain import KERNELS, SOURCE

    declared, emitted = _compiled(tmp_path, SOURCE, target, [])
    assert declared == set(KERNELS)
    assert emitted == declared
