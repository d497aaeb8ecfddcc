"""Which OpenCL device the renderer takes (appliance/xray/device.py `pick_device`): the first
whose compiler builds drr.cl on this processor; one that cannot is skipped, and with none
that can, the command says so in one line naming each device and what to install.

Ground truth: each device's build of drr.cl, and each of its kernels made, tried here with
pyopencl alone, one device a process (a build can kill its process), whose ICD loader sees
only the vendor files the test chose (OCL_ICD_VENDORS): the pyopencl
wheel's own PoCL (whose LLVM may not know a processor newer than it) first, then this
machine's installed ones. On a machine where every device builds, the same tests hold with
the first device picked.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from importlib import resources
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest
import SimpleITK as sitk

from appliance.xray.device import ClDevice, pick_device
from appliance.xray.truth.analytic import box_volume

REPO = Path(__file__).resolve().parents[1]
WHEEL_ICD = Path(cl.__file__).parent / ".libs" / "pocl.icd"
SYSTEM_VENDORS = Path("/etc/OpenCL/vendors")
DRR_CL = resources.files("appliance.xray").joinpath("drr.cl").read_text()

#: Run with the chosen vendors: this process's CPU devices, each once, as "platform:device"
#: indices with their names and versions (a loader that reads one PoCL's vendor file twice
#: lists its platform twice, the same device in both).
LIST = """
import json
import pyopencl as cl
devices, seen = [], set()
for i, p in enumerate(cl.get_platforms()):
    for j, d in enumerate(p.get_devices()):
        if d.type & cl.device_type.CPU and d.int_ptr not in seen:
            seen.add(d.int_ptr)
            devices.append([f"{i}:{j}", d.name.strip(), p.version.strip()])
print(json.dumps(devices))
"""

#: Run with the chosen vendors, one device a process (argv: its indices): its build of drr.cl
#: with the CPU's option, twice (the second from PoCL's kernel cache), each kernel the source
#: declares made from each, and the build log's "error:" lines in the compiler's order. Nothing
#: is released: PoCL 3.0 on a processor its LLVM does not know aborts the process releasing a
#: build that made no kernels.
TRY = """
import json, os, re, sys
from importlib import resources
import pyopencl as cl
source = resources.files("appliance.xray").joinpath("drr.cl").read_text()
i, j = (int(k) for k in sys.argv[1].split(":"))
d = cl.get_platforms()[i].get_devices()[j]
answer, kept = {"builds": True, "errors": []}, []
try:
    for again in range(2):      # the renderer's build is the second, read from PoCL's cache
        program = cl.Program(cl.Context([d]), source)
        kept.append(program)
        program.build(options=["-DUNALIGNED_PAIRS"])
        kernels = [cl.Kernel(program, name) for name in re.findall(r"kernel void (\\w+)\\(", source)]
        answer["kernels"] = len(kernels)
except cl.Error as e:
    answer = {"builds": False, "errors": [ln.strip() for ln in str(e).splitlines() if "error:" in ln]}
print(json.dumps(answer), flush=True)
os._exit(0)
"""

#: Run with the chosen vendors: pick_device's answer, the device's name and version or its
#: refusal, then the warnings it logged.
PICK = """
import json, logging
from appliance.errors import FluorosimError
from appliance.xray.device import pick_device
warned = []
handler = logging.Handler(logging.WARNING)
handler.emit = lambda record: warned.append(record.getMessage())
logging.getLogger("appliance").addHandler(handler)
try:
    d = pick_device("cpu")
    picked = [d.name.strip(), d.platform.version.strip()]
except FluorosimError as e:
    picked = str(e)
print(json.dumps([picked, warned]))
"""


def vendors(tmp_path: Path, system: bool) -> dict[str, str]:
    """An environment whose ICD loader reads `tmp_path`'s vendor files: the wheel's PoCL first
    (the loader takes them in file-name order), then, with `system`, this machine's."""
    assert WHEEL_ICD.is_file(), f"pyopencl[pocl] ships its PoCL's vendor file as {WHEEL_ICD}"
    folder = tmp_path / "vendors"
    folder.mkdir()
    (folder / "0-wheel.icd").write_text(WHEEL_ICD.read_text())
    if system and SYSTEM_VENDORS.is_dir():
        for icd in sorted(SYSTEM_VENDORS.glob("*.icd")):
            (folder / f"1-{icd.name}").write_text(icd.read_text())
    return {**os.environ, "OCL_ICD_VENDORS": str(folder)}


def python(script: str, env: dict[str, str], *args: str):
    out = subprocess.run([sys.executable, "-c", script, *args], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[-1])


def tried(env: dict[str, str]) -> list[list]:
    """Each CPU device the vendors give, [name, version, builds, its build's error lines], from a
    build of drr.cl in a process of its own (a device whose build kills that process cannot)."""
    devices = []
    for spec, name, version in python(LIST, env):
        out = subprocess.run([sys.executable, "-c", TRY, spec], cwd=REPO, env=env, capture_output=True, text=True,
                             timeout=300)
        lines = out.stdout.splitlines()
        answer = json.loads(lines[-1]) if lines else {"builds": False, "errors": []}
        assert not answer["builds"] or answer["kernels"] == DRR_CL.count("\nkernel void "), answer
        devices.append([name, version, answer["builds"], answer["errors"]])
    return devices


@pytest.fixture(scope="module")
def listed(tmp_path_factory) -> dict:
    """Each device's own build with the wheel's PoCL first and this machine's vendors after it,
    and pick_device's answer there, from an empty kernel cache: the probe's builds are the first
    (a PoCL may make a fresh build's kernels and not those of the build it cached)."""
    env = {**vendors(tmp_path_factory.mktemp("icd"), system=True), "POCL_CACHE_DIR": str(tmp_path_factory.mktemp("kcache"))}
    picked, warned = python(PICK, env)
    return {"devices": tried(env), "picked": picked, "warned": warned}


def test_a_device_that_cannot_build_is_skipped_for_the_first_that_can(listed):
    devices, picked = listed["devices"], listed["picked"]
    assert devices and devices[0][1].startswith("OpenCL") and "PoCL" in devices[0][1]      # the wheel's, first
    builders = [d[:2] for d in devices if d[2]]
    if builders:
        assert picked == builders[0]
        passed_over = devices[:[d[:2] for d in devices].index(builders[0])]
        assert len(listed["warned"]) == len(passed_over)     # each named in the log, why included
        for (name, version, *_), line in zip(passed_over, listed["warned"]):
            assert f"skipped, it cannot compile the renderer's kernels: {name} ({version}): " in line
    else:
        assert isinstance(picked, str) and "pocl-opencl-icd" in picked
        assert all(name in picked for name, *_ in devices)


def render_a_box(tmp_path: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """`fluorosim render` of a small water box in `tmp_path`, to li.npy there."""
    vol, _, _ = box_volume((8, 8, 8), (5.0, 5.0, 5.0), (2, 2, 2), (5, 5, 5), hu=0)
    img = sitk.GetImageFromArray(vol.hu)
    img.SetSpacing((5.0, 5.0, 5.0))
    img.SetOrigin(tuple(vol.T_ct_from_voxel[:3, 3]))
    sitk.WriteImage(img, str(tmp_path / "box.nii.gz"))
    (tmp_path / "pose.yaml").write_text("T_xray_from_ct:\n  - [1, 0, 0, 0]\n  - [0, 1, 0, 0]\n  - [0, 0, 1, 750]\n"
                                        "  - [0, 0, 0, 1]\n")
    return subprocess.run([sys.executable, "-m", "appliance", "render", "--volume", "box.nii.gz", "--fluoroscope",
                           str(REPO / "configs/fluoroscopes/generic-flat-detector.yaml"), "--pose", "pose.yaml",
                           "--quantity", "line-integral", "--size", "32", "--output", "li.npy"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)


def test_with_no_device_that_builds_the_command_says_so_in_one_line(tmp_path, listed):
    """`fluorosim render` with only the wheel's PoCL (the probe's first device): on a processor
    its LLVM does not know, it cannot build, and the command exits with one line naming the
    device and pocl-opencl-icd, no traceback; where it builds, the render succeeds."""
    wheel = listed["devices"][0]
    out = render_a_box(tmp_path, vendors(tmp_path, system=False))
    if wheel[2]:
        assert out.returncode == 0, out.stderr
        assert np.load(tmp_path / "li.npy").max() > 0
        return
    lines = out.stderr.strip().splitlines()
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert len(lines) == 1, lines
    assert lines[0].startswith("fluorosim: no OpenCL device") and "pocl-opencl-icd" in lines[0]
    assert f"{wheel[0]} ({wheel[1]})" in lines[0]
    assert not (tmp_path / "li.npy").exists()


@pytest.mark.parametrize("device", ["auto", "cpu"])
def test_the_device_picked_here_builds_drr_cl_with_and_without_blending(device):
    d = pick_device(device)
    options = ["-DUNALIGNED_PAIRS"] if d.type & cl.device_type.CPU else []
    for extra in ([], ["-DBLEND"]):
        cl.Program(cl.Context([d]), DRR_CL).build(options=options + extra)
    if device == "cpu":                         # PoCL's device, never a GPU listed beside it
        assert d.type & cl.device_type.CPU and not d.type & cl.device_type.GPU
    assert ClDevice(device).device.int_ptr == d.int_ptr


#: Run with the chosen vendors: how many build probes three pick_device("cpu") calls at once
#: start, then each of two more (every process device.py starts counted, the probes real).
COUNTED = """
import json
from appliance.errors import FluorosimError
from appliance.xray import device
started = []
run = device.subprocess.run
def counted(*args, **kwargs):
    started.append(1)
    return run(*args, **kwargs)
device.subprocess.run = counted
def pick():
    try:
        device.pick_device("cpu")
    except FluorosimError:
        pass
import threading
together = [threading.Thread(target=pick) for _ in range(3)]      # three renderers made at once
for t in together:
    t.start()
for t in together:
    t.join()
per_call = [len(started)]
for _ in range(2):
    before = len(started)
    pick()
    per_call.append(len(started) - before)
print(json.dumps(per_call))
"""


def test_each_device_is_tried_once_a_process(tmp_path, listed):
    """The first picks, three at once, probe the devices in order up to the first that builds
    (all of them when none does) once, in one process unless a build kills it; later picks
    probe nothing again."""
    builds = [d[2] for d in listed["devices"]]
    tried = builds.index(True) + 1 if True in builds else len(builds)
    first, *later = python(COUNTED, vendors(tmp_path, system=True))
    assert 1 <= first <= tried and later == [0, 0]


def test_a_device_that_cannot_build_is_named_with_its_compilers_first_error(tmp_path):
    """PoCL adds POCL_EXTRA_BUILD_FLAGS to every build: a macro that turns get_global_id into
    two undeclared names breaks drr.cl with several errors, the first in PoCL's own header, the
    last naming the second name. The refusal names each device with its compiler's first
    error line (the cause; the rest follow from it), never its last."""
    env = {**vendors(tmp_path, system=True),
           "POCL_EXTRA_BUILD_FLAGS": "-Dget_global_id(x)=(x+undeclared_first+undeclared_second)"}
    devices = tried(env)
    refusal, _ = python(PICK, env)
    assert isinstance(refusal, str) and refusal.startswith("no OpenCL device here can compile kernels")
    several = [(name, version, errors) for name, version, _, errors in devices if len(set(errors)) >= 2]
    assert several, devices                     # Debian's PoCL reports each error on a line of its own
    for name, version, errors in several:
        assert f"{name} ({version}): {errors[0]}" in refusal
        assert errors[-1] not in refusal


#: On PYTHONPATH as sitecustomize: a build probe whose first device is $KILL_PROBE_OF aborts at
#: once, as a compiler that takes its process with it does (the abort is real, only its cause is
#: staged; a later probe starting from another device runs as it would).
KILLER = """
import os, signal, sys
if sys.argv[0].endswith("build_probe.py") and sys.argv[1:2] == [os.environ.get("KILL_PROBE_OF")]:
    os.kill(os.getpid(), signal.SIGABRT)
"""


def test_a_device_whose_probe_dies_is_named_by_its_signal_and_the_next_is_tried(tmp_path, listed):
    """The first device's probe process is killed by SIGABRT: the pick goes on, in a new probe,
    to the devices after it, and picks the first of them that builds by the ground truth; where
    none does, the refusal names the first device with the signal and each after it with its
    own reason. Both with this machine's vendors and with the wheel's PoCL alone."""
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(KILLER)
    for system in (True, False):
        folder = tmp_path / f"system-{system}"
        folder.mkdir()
        env = vendors(folder, system=system)
        devices = listed["devices"] if system else tried(env)
        spec, name, version = python(LIST, env)[0]
        picked, _ = python(PICK, {**env, "PYTHONPATH": str(tmp_path / "site"), "KILL_PROBE_OF": spec})
        builders = [d[:2] for d in devices[1:] if d[2]]
        if builders:
            assert picked == builders[0]
            continue
        assert isinstance(picked, str), picked
        first, *rest = picked[picked.index("machine (") + 9:picked.rindex("); install")].split("; ")
        assert f"{name} ({version}): its compiler killed the probe process (SIGABRT" in first
        assert len(rest) == len(devices) - 1 and not any("SIGABRT" in part for part in rest)


#: On PYTHONPATH as sitecustomize: a build probe's standard output opens with lines a driver
#: might print there (POCL_DEBUG and some ICDs write to it), one of them JSON of another shape.
NOISY = """
import sys
if sys.argv[0].endswith("build_probe.py"):
    print("{ driver banner", flush=True)
    print('{"version": 3}', flush=True)
    print("[pocl] debug line", flush=True)
"""


def test_what_a_driver_prints_beside_the_probes_answers_is_not_taken_for_one(tmp_path, listed):
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(NOISY)
    picked, _ = python(PICK, {**vendors(tmp_path, system=True), "PYTHONPATH": str(tmp_path / "site")})
    assert picked == listed["picked"]


@pytest.fixture
def full_folder(tmp_path):
    """A folder on a 64 KiB tmpfs filled to the last block (a full disk), where this process
    may mount one; else the test using it is skipped."""
    folder = tmp_path / "full"
    folder.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(folder)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root): the full disk is not staged")
    try:
        with open(folder / "fill", "wb", buffering=0) as f:
            with contextlib.suppress(OSError):
                while True:
                    f.write(bytes(4096))
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True)


@pytest.mark.parametrize("where", ["under a file", "on a full disk"])
def test_a_kernel_cache_that_cannot_be_written_is_named_in_one_line(tmp_path, request, where):
    """PoCL compiles into its kernel cache (POCL_CACHE_DIR): where that cannot be written, it
    lists no device or fails every build. The command says so in one line naming the folder and
    what to do, not "install another OpenCL", with no traceback and no image written."""
    if where == "under a file":
        (tmp_path / "a-file").write_text("")
        cache = tmp_path / "a-file" / "pocl"
    else:
        cache = request.getfixturevalue("full_folder") / "pocl"
    work = tmp_path / "work"
    work.mkdir()
    out = render_a_box(work, {**os.environ, "POCL_CACHE_DIR": str(cache)})
    lines = out.stderr.strip().splitlines()
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert lines[-1].startswith("fluorosim: no OpenCL device can compile kernels: PoCL's kernel cache"), lines
    assert str(cache) in lines[-1] and "POCL_CACHE_DIR" in lines[-1]
    assert len([ln for ln in lines if ln.startswith("fluorosim:")]) == 1
    assert not (work / "li.npy").exists()
