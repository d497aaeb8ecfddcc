"""provisioning/install.sh: the tree it installs, checked file by file; dry runs; idempotence."""

from __future__ import annotations

import os
import pwd
import shutil
import stat
import subprocess
import tempfile
from pathlib import Path

import pytest

from appliance.config import ApplianceProfile, load_profile, validate_paths
from appliance.records.identity import read_device_uid

REPO = Path(__file__).resolve().parents[1]
INSTALL = REPO / "provisioning" / "install.sh"
PROFILE_KINDS = ("fluoroscopes", "cases", "phantoms", "keymaps", "webcams", "exercises")


def world_readable_copy() -> Path:
    """The checkout's provisioning inputs copied where any user can read them.

    A checkout may sit in a home folder only its owner can enter; the script run as another
    user must then read a copy, so that a refusal in the test means the script refused,
    never that the user could not read it."""
    top = Path(tempfile.mkdtemp(prefix="fluorosim-provisioning-"))
    top.chmod(0o755)
    copy = top / "checkout"
    shutil.copytree(REPO, copy, symlinks=True,
                    ignore=shutil.ignore_patterns(".git", ".venv", "var", "__pycache__", "*.pyc", ".pytest_cache",
                                                  "*.egg-info", "build", ".mypy_cache", ".ruff_cache", "mutants"))
    for dirpath, _dirnames, filenames in os.walk(copy):
        os.chmod(dirpath, 0o755)
        for name in filenames:
            path = Path(dirpath) / name
            if not path.is_symlink():
                path.chmod(path.stat().st_mode | 0o444)
    return copy


def run_install(*args, user: str | None = None) -> subprocess.CompletedProcess:
    script = INSTALL
    if user:
        script = world_readable_copy() / "provisioning" / "install.sh"
    argv = ["bash", str(script), *args]
    if user:
        entry = pwd.getpwnam(user)
        argv = ["setpriv", f"--reuid={entry.pw_uid}", f"--regid={entry.pw_gid}", "--clear-groups", *argv]
    try:
        return subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd="/")
    finally:
        if user:
            shutil.rmtree(script.parents[1].parent, ignore_errors=True)


def snapshot(root: Path) -> dict[str, tuple]:
    """Every path under root: (kind, mode, content or link target)."""
    tree = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            rel = str(p.relative_to(root))
            if stat.S_ISLNK(st.st_mode):
                tree[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                tree[rel] = ("dir", stat.S_IMODE(st.st_mode))
            else:
                tree[rel] = ("file", stat.S_IMODE(st.st_mode), p.read_bytes())
    return tree


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    root = tmp_path_factory.mktemp("image") / "root"
    result = run_install("--root", str(root))
    assert result.returncode == 0, result.stderr
    return root, result.stdout


def test_units_rules_and_user_definition_are_installed(installed):
    root, _ = installed
    for shipped, dest in (("systemd/fluorosim.service", "etc/systemd/system/fluorosim.service"),
                          ("systemd/99-fluorosim.rules", "etc/udev/rules.d/99-fluorosim.rules"),
                          ("provisioning/sysusers-fluorosim.conf", "usr/lib/sysusers.d/fluorosim.conf"),
                          ("provisioning/modules-fluorosim.conf", "etc/modules-load.d/fluorosim.conf"),
                          ("provisioning/journald-fluorosim.conf", "etc/systemd/journald.conf.d/fluorosim.conf"),
                          ("provisioning/grub-fluorosim.cfg", "etc/default/grub.d/fluorosim.cfg")):
        target = root / dest
        assert target.read_bytes() == (REPO / shipped).read_bytes(), dest
        assert stat.S_IMODE(target.stat().st_mode) == 0o644, dest


def test_profiles_in_etc_name_the_real_devices_and_validate(installed):
    root, _ = installed
    etc = root / "etc/fluorosim"
    for kind in PROFILE_KINDS:
        shipped = sorted(p.name for p in (REPO / "configs" / kind).iterdir() if p.is_file())
        assert shipped and sorted(p.name for p in (etc / kind).iterdir()) == shipped, kind
        for name in shipped:
            assert (etc / kind / name).read_bytes() == (REPO / "configs" / kind / name).read_bytes()
    appliance = etc / "appliance.yaml"
    assert validate_paths([appliance]) == [], "the installed profile and every profile it names are valid"
    profile = load_profile(appliance, ApplianceProfile)
    assert profile.devices.camera.source == "/dev/fluorosim/camera"
    assert profile.devices.keypad.source == "/dev/fluorosim/keypad"
    assert profile.devices.pedal.source == "/dev/fluorosim/pedal"
    assert profile.devices.display.target == "/dev/fb0"
    assert profile.data_dir == "/var/lib/fluorosim"
    # The Device Observer UID, made once at provisioning, where the profile looks for it.
    assert read_device_uid(etc / profile.dicom.identity_file).startswith("2.25.")


def test_code_state_journal_and_boot_settings(installed):
    root, _ = installed
    src = root / "opt/fluorosim/src"
    for rel in ("pyproject.toml", "appliance/cli.py", "drivers/framebuffer.py", "appliance/display/compositor.py"):
        assert (src / rel).read_bytes() == (REPO / rel).read_bytes(), rel
    assert not list(src.rglob("__pycache__")) and not (src / "tests").exists()
    for d in ("var/lib/fluorosim", "var/log/fluorosim", "var/cache/fluorosim"):
        assert stat.S_IMODE((root / d).stat().st_mode) == 0o750, d
    assert (root / "var/log/journal").is_dir()
    assert "Storage=persistent" in (root / "etc/systemd/journald.conf.d/fluorosim.conf").read_text()
    system = root / "etc/systemd/system"
    # What `systemctl enable`, `set-default multi-user.target` and `mask getty@tty1` write.
    assert os.readlink(system / "multi-user.target.wants/fluorosim.service") == "/etc/systemd/system/fluorosim.service"
    assert os.readlink(system / "default.target").endswith("/systemd/system/multi-user.target")
    assert os.readlink(system / "getty@tty1.service") == "/dev/null"
    assert os.readlink(system / "autovt@tty1.service") == "/dev/null"
    assert "quiet" in (root / "etc/default/grub.d/fluorosim.cfg").read_text()


def test_code_is_a_release_made_current_by_one_symlink(installed):
    root, out = installed
    opt = root / "opt/fluorosim"
    current = os.readlink(opt / "current")
    assert current.startswith("releases/") and (opt / current / "src/appliance/cli.py").is_file()
    # The unit's paths go through `current`, so one rename swaps code and virtualenv together.
    assert os.readlink(opt / "src") == "current/src" and os.readlink(opt / "venv") == "current/venv"
    assert "atomic rename of /opt/fluorosim/current" in out
    assert not list(opt.glob(".current.new")) and not list(opt.glob("releases/*/.src.new"))


def test_a_new_release_keeps_the_one_before_and_drops_older(tmp_path):
    root, src = tmp_path / "root", tmp_path / "checkout"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".venv", ".git", "var", "__pycache__", "tests"))
    ids = []
    for n in range(3):
        (src / "README.md").write_text(f"release {n}\n")
        result = subprocess.run(["bash", str(src / "provisioning/install.sh"), "--root", str(root)],
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, result.stderr
        ids.append(os.readlink(root / "opt/fluorosim/current").removeprefix("releases/"))
    assert len(set(ids)) == 3
    assert sorted(p.name for p in (root / "opt/fluorosim/releases").iterdir()) == sorted(ids[1:])
    assert (root / "opt/fluorosim/src/README.md").read_text() == "release 2\n"


def test_lock_pins_every_dependency_with_a_hash(installed):
    root, _ = installed
    lock = (REPO / "provisioning/requirements.lock").read_text()
    entries = [e for e in lock.replace("\\\n", " ").splitlines() if e.strip() and not e.startswith("#")]
    names = {e.split("==")[0].lower() for e in entries}
    assert all("==" in e and "--hash=sha256:" in e for e in entries), entries
    assert "file:" not in lock and "http" not in lock       # the hashes, not a location, decide
    # Every dependency pyproject.toml names is in the lock.
    import tomllib
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    import re

    def normal(name: str) -> str:   # PEP 503
        return re.sub(r"[-_.]+", "-", name).lower()
    for dep in deps:
        name = normal(re.match(r"[A-Za-z0-9._-]+", dep).group(0))
        assert name in {normal(n) for n in names}, name
    assert "--require-hashes" in (REPO / "provisioning/install.sh").read_text()


def test_consoles_and_boot_loader_are_locked(installed):
    root, out = installed
    system = root / "etc/systemd/system"
    for n in range(1, 7):
        assert os.readlink(system / f"getty@tty{n}.service") == "/dev/null"
        assert os.readlink(system / f"autovt@tty{n}.service") == "/dev/null"
    assert os.readlink(system / "ctrl-alt-del.target") == "/dev/null"
    assert "NAutoVTs=0" in (root / "etc/systemd/logind.conf.d/fluorosim.conf").read_text()
    grub = root / "etc/grub.d/01_fluorosim_password"
    assert stat.S_IMODE(grub.stat().st_mode) == 0o755 and "password_pbkdf2" in grub.read_text()
    assert os.readlink(system / "sockets.target.wants/fluorosim-seal.socket") == "/etc/systemd/system/fluorosim-seal.socket"
    assert "skipped (--root): set the GRUB menu password" in out


def test_grub_password_script_emits_the_superuser(tmp_path):
    script = (REPO / "provisioning/grub-fluorosim-password").read_text()
    hash_file = tmp_path / "grub.pbkdf2"
    hash_file.write_text("grub.pbkdf2.sha512.10000.AB.CD\n")
    result = subprocess.run(["sh", "-c", script.replace("/etc/fluorosim-seal/grub.pbkdf2", str(hash_file))],
                            capture_output=True, text=True)
    assert result.returncode == 0
    assert result.stdout.splitlines() == ['set superusers="fluorosim-admin"',
                                          "password_pbkdf2 fluorosim-admin grub.pbkdf2.sha512.10000.AB.CD"]


def test_nvidias_compute_driver_is_loaded_at_boot_only_where_the_tree_has_it(installed, tmp_path):
    """The modules-load file for NVIDIA's driver (nvidia-uvm, which its OpenCL needs and the
    sandboxed service cannot load itself) is installed where the tree being installed holds
    that module (as DKMS builds it), and taken away again once the module is gone: a module
    named there but missing fails the boot's module loading."""
    conf = "etc/modules-load.d/fluorosim-nvidia.conf"
    root, out = installed
    assert not (root / conf).exists() and "no NVIDIA driver (nvidia-uvm.ko)" in out
    image = tmp_path / "root"
    module = image / "lib/modules/6.1.0-28-amd64/updates/dkms/nvidia-uvm.ko.xz"
    module.parent.mkdir(parents=True)
    module.write_bytes(b"")                 # the driver package's file; its content is not read
    assert run_install("--root", str(image)).returncode == 0
    assert (image / conf).read_bytes() == (REPO / "provisioning/modules-fluorosim-nvidia.conf").read_bytes()
    loaded = [ln for ln in (image / conf).read_text().splitlines() if ln and not ln.startswith("#")]
    assert loaded == ["nvidia", "nvidia-uvm"]
    module.unlink()
    again = run_install("--root", str(image))
    assert again.returncode == 0 and not (image / conf).exists()


def test_system_changes_are_listed_as_skipped_under_root(installed):
    _, out = installed
    skipped = [line for line in out.splitlines() if line.startswith("skipped (--root):")]
    for word in ("system packages", "systemd-sysusers", "virtualenv", "chown", "systemctl daemon-reload", "update-grub",
                 "systemctl restart fluorosim.service", "systemd-journald"):
        assert any(word in line for line in skipped), word


def test_the_installed_unit_verifies_in_the_installed_tree(installed, tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed (Debian package: systemd)")
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    system_units = next(p for p in (Path("/usr/lib/systemd/system"), Path("/lib/systemd/system")) if p.is_dir())
    shutil.copytree(system_units, root / "usr/lib/systemd/system", symlinks=True, dirs_exist_ok=True)
    exe = root / "opt/fluorosim/current/venv/bin/fluorosim"   # the release's virtualenv pip would have made
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    kill = root / "bin/kill"     # ExecReload=
    kill.parent.mkdir(parents=True, exist_ok=True)
    kill.write_text("#!/bin/sh\n")
    kill.chmod(0o755)
    result = subprocess.run([analyze, "verify", f"--root={root}", "fluorosim.service"], capture_output=True, text=True)
    assert result.returncode == 0 and result.stderr.strip() == "", result.stderr


def test_sysusers_definition_creates_the_user_with_its_groups(installed, tmp_path):
    sysusers = shutil.which("systemd-sysusers")
    if sysusers is None:
        pytest.skip("systemd-sysusers is not installed (Debian package: systemd)")
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    result = subprocess.run([sysusers, f"--root={root}", str(installed[0] / "usr/lib/sysusers.d/fluorosim.conf")],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    passwd = {line.split(":")[0]: line.split(":") for line in (root / "etc/passwd").read_text().splitlines()}
    assert passwd["fluorosim"][5] == "/var/lib/fluorosim" and passwd["fluorosim"][6].endswith("nologin")
    groups = {line.split(":")[0]: line.split(":")[3].split(",") for line in (root / "etc/group").read_text().splitlines()}
    for group in ("video", "input", "dialout", "audio"):
        assert "fluorosim" in groups[group], group
    assert "fluorosim" not in groups.get("sudo", []) and "fluorosim" not in groups.get("root", [])


def test_second_run_changes_nothing_and_keeps_local_profile_edits(tmp_path):
    root = tmp_path / "root"
    assert run_install("--root", str(root)).returncode == 0
    edited = root / "etc/fluorosim/appliance.yaml"
    edited.write_text(edited.read_text().replace("operator: trainee", "operator: dr-smith"))
    (root / "etc/fluorosim/fluoroscopes/generic-ii-carm.yaml").write_text("# calibrated on site\n")
    (root / "etc/systemd/system/fluorosim.service").write_text("stale\n")
    before = snapshot(root)
    second = run_install("--root", str(root))
    assert second.returncode == 0, second.stderr
    after = snapshot(root)
    assert "operator: dr-smith" in edited.read_text()
    assert (root / "etc/fluorosim/fluoroscopes/generic-ii-carm.yaml").read_text() == "# calibrated on site\n"
    assert (root / "etc/systemd/system/fluorosim.service").read_bytes() == (REPO / "systemd/fluorosim.service").read_bytes()
    changed = {k for k in set(before) | set(after) if before.get(k) != after.get(k)}
    assert changed == {"etc/systemd/system/fluorosim.service"}
    third = run_install("--root", str(root))
    assert third.returncode == 0 and snapshot(root) == after


def test_dry_run_lists_every_step_and_writes_nothing(tmp_path):
    root = tmp_path / "root"
    result = run_install("--dry-run", "--root", str(root))
    assert result.returncode == 0, result.stderr
    assert not root.exists()
    lines = result.stdout.splitlines()
    assert sum(line.startswith("would: ") for line in lines) >= 8
    assert any(line.startswith("skipped (--root): install system packages") for line in lines)


def test_dry_run_on_this_machine_lists_the_system_steps(tmp_path):
    # As an unprivileged user, so that a dry run that did something would fail instead of changing this machine.
    if shutil.which("setpriv") is None or os.geteuid() != 0:
        pytest.skip("needs root and setpriv (util-linux) to run the dry run as user nobody")
    result = run_install("--dry-run", user="nobody")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    for step in ("install system packages", "systemd-sysusers", "virtualenv", "/etc/systemd/system/fluorosim.service",
                 "udev rules", "journal", "enable fluorosim.service", "no getty on tty1", "update-grub",
                 "systemctl restart fluorosim.service"):
        assert step in out, step
    assert "skipped" not in out and "==>" not in out


def test_refuses_to_change_the_system_unless_root():
    if shutil.which("setpriv") is None or os.geteuid() != 0:
        pytest.skip("needs root and setpriv (util-linux) to run as user nobody")
    result = run_install(user="nobody")
    assert result.returncode == 2 and "run as root" in result.stderr


def test_bad_arguments_print_usage():
    for args in (["--root"], ["--frobnicate"]):
        result = run_install(*args)
        assert result.returncode == 2 and "usage:" in result.stderr, args
