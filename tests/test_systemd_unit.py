"""The systemd unit, checked by systemd's own analyzer, and the udev rules, checked against udev(7)."""

from __future__ import annotations

import fnmatch
import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "fluorosim.service"
RULES = REPO / "systemd" / "99-fluorosim.rules"
EXEC = "/opt/fluorosim/venv/bin/fluorosim"

ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed (Debian package: systemd)")


def unit_settings(text: str) -> dict[tuple[str, str], list[str]]:
    """(section, key) -> values in order; systemd keys may repeat (DeviceAllow=, Environment=)."""
    settings: dict[tuple[str, str], list[str]] = {}
    section = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        settings.setdefault((section, key.strip()), []).append(value.strip())
    return settings


def one(settings, section, key):
    values = settings.get((section, key), [])
    assert len(values) == 1, f"[{section}] {key}= set {len(values)} times"
    return values[0]


def seconds(value: str) -> float:
    units = {"ms": 0.001, "s": 1, "sec": 1, "min": 60, "m": 60}
    m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([a-z]*)", value)
    assert m, value
    return float(m.group(1)) * units.get(m.group(2) or "s", 1)


def root_with_unit(tmp_path: Path, unit_text: str) -> Path:
    """A file-system tree holding systemd's own units, the unit under test and an executable at ExecStart."""
    root = tmp_path / "root"
    system_units = next((p for p in (Path("/usr/lib/systemd/system"), Path("/lib/systemd/system")) if p.is_dir()), None)
    if system_units is None:
        pytest.skip("no systemd unit folder on this machine to verify against")
    shutil.copytree(system_units, root / "usr/lib/systemd/system", symlinks=True)
    (root / "etc/systemd/system").mkdir(parents=True)
    (root / "etc/systemd/system/fluorosim.service").write_text(unit_text)
    for helper in ("fluorosim-seal.socket", "fluorosim-seal.service"):
        shutil.copy(REPO / "systemd" / helper, root / "etc/systemd/system" / helper)
    exe = root / EXEC.lstrip("/")
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\nexit 0\n")
    exe.chmod(0o755)
    kill = root / "bin/kill"     # ExecReload=
    kill.parent.mkdir(parents=True, exist_ok=True)
    kill.write_text("#!/bin/sh\nexit 0\n")
    kill.chmod(0o755)
    return root


def verify(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run([ANALYZE, "verify", f"--root={root}", "fluorosim.service"], capture_output=True, text=True)


@needs_analyze
def test_systemd_analyze_verify_is_clean_for_the_unit_as_shipped(tmp_path):
    # --root looks for ExecStart's binary inside the tree, so the shipped file is verified unchanged.
    result = verify(root_with_unit(tmp_path, UNIT.read_text()))
    assert result.returncode == 0 and result.stdout.strip() == "" and result.stderr.strip() == "", result.stderr


@needs_analyze
def test_verify_does_report_a_broken_unit(tmp_path):
    # The check above can fail: a misspelt key and a missing binary are reported.
    broken = UNIT.read_text().replace("WatchdogSec=", "WatchdogSecs=")
    result = verify(root_with_unit(tmp_path, broken))
    assert "Unknown key" in result.stderr and "WatchdogSecs" in result.stderr
    root = root_with_unit(tmp_path / "b", UNIT.read_text())
    (root / EXEC.lstrip("/")).unlink()
    result = verify(root)
    assert result.returncode != 0 and "is not executable" in result.stderr


# The exposure each shipped unit reached (systemd 252); a change that raises one fails here.
# The service keeps AF_INET (DICOM), its devices, @resources (PoCL's affinity) and W^X off
# (OpenCL's compiler); the seal helper stays root to read its key (see the unit files).
EXPOSURE_REACHED = {"fluorosim.service": 1.4, "fluorosim-seal.service": 0.9}


@needs_analyze
@pytest.mark.parametrize("unit", sorted(EXPOSURE_REACHED))
def test_security_exposure_stays_at_what_was_reached(unit):
    bar = EXPOSURE_REACHED[unit]
    result = subprocess.run([ANALYZE, "security", "--offline=yes", f"--threshold={round(bar * 10)}",
                             str(REPO / "systemd" / unit)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr
    m = re.search(rf"Overall exposure level for {re.escape(unit)}: (\d+\.\d+)", result.stdout)
    assert m, result.stdout[-500:]
    assert float(m.group(1)) <= bar


@needs_analyze
def test_security_threshold_fails_a_bare_unit(tmp_path):
    bare = tmp_path / "bare.service"
    bare.write_text("[Service]\nType=notify\nExecStart=/bin/true\n")
    result = subprocess.run([ANALYZE, "security", "--offline=yes", "--threshold=15", str(bare)],
                            capture_output=True, text=True)
    assert result.returncode != 0
    assert float(re.search(r"Overall exposure level for bare\.service: (\d+\.\d+)", result.stdout).group(1)) > 5


def test_unit_runs_the_appliance_as_a_supervised_notify_service():
    s = unit_settings(UNIT.read_text())
    assert one(s, "Service", "ExecStart") == f"{EXEC} run --config /etc/fluorosim/appliance.yaml"
    assert one(s, "Service", "Type") == "notify"
    assert one(s, "Service", "NotifyAccess") == "main"
    assert 2 <= seconds(one(s, "Service", "WatchdogSec")) <= 30
    assert one(s, "Service", "Restart") == "always"
    assert int(one(s, "Unit", "StartLimitBurst")) >= 3 and seconds(one(s, "Unit", "StartLimitIntervalSec")) > 0
    # Restarts must fit inside the start-limit window or the limit never triggers.
    assert seconds(one(s, "Service", "RestartSec")) * int(one(s, "Unit", "StartLimitBurst")) < \
        seconds(one(s, "Unit", "StartLimitIntervalSec"))
    assert seconds(one(s, "Service", "TimeoutStopSec")) >= 2   # the daemon exits within 2 s of SIGTERM
    assert one(s, "Install", "WantedBy") == "multi-user.target"
    # `systemctl reload` sends the SIGHUP the daemon reloads its profiles on.
    assert one(s, "Service", "ExecReload") == "/bin/kill -HUP $MAINPID"


def test_unit_user_groups_devices_and_writable_state():
    s = unit_settings(UNIT.read_text())
    assert one(s, "Service", "User") == "fluorosim"
    groups = set(one(s, "Service", "SupplementaryGroups").split())
    assert {"video", "input", "dialout"} <= groups <= {"video", "input", "dialout", "audio", "render"}
    assert one(s, "Service", "ProtectSystem") == "strict"
    assert one(s, "Service", "StateDirectory") == "fluorosim"
    assert one(s, "Service", "LogsDirectory") == "fluorosim"
    assert ("Service", "ReadWritePaths") not in s, "writable state only under the managed directories"
    # PrivateDevices= would hide the device nodes, PrivateNetwork= the udev netlink events.
    assert ("Service", "PrivateDevices") not in s and ("Service", "PrivateNetwork") not in s
    assert one(s, "Service", "DevicePolicy") == "closed"
    allowed = {v.split()[0]: v.split()[1] for v in s[("Service", "DeviceAllow")]}
    for device in ("char-input", "char-video4linux", "char-ttyUSB", "char-ttyACM", "/dev/fb0"):
        assert allowed.get(device) == "rw", device
    # The GPU's OpenCL: render nodes, NVIDIA's nodes under either name of its major, its UVM, AMD's KFD.
    for device in ("char-drm", "char-nvidia", "char-nvidia-frontend", "char-nvidia-uvm", "char-kfd"):
        assert allowed.get(device) == "rw", device
    assert one(s, "Service", "IPAddressDeny") == "any"
    assert "AF_NETLINK" in one(s, "Service", "RestrictAddressFamilies").split()
    assert one(s, "Service", "CapabilityBoundingSet") == ""
    env = dict(v.split("=", 1) for v in s[("Service", "Environment")])
    cache = one(s, "Service", "CacheDirectory")
    assert env["POCL_CACHE_DIR"].startswith(f"/var/cache/{cache}/"), "PoCL needs a writable kernel cache"


# ---------------------------------------------------------------------------- udev rules

# udev(7): match keys, assignment keys (some take {attribute}), and their operators.
MATCH_KEYS = {"ACTION", "DEVPATH", "KERNEL", "NAME", "SYMLINK", "SUBSYSTEM", "DRIVER", "ATTR", "SYSCTL", "KERNELS",
              "SUBSYSTEMS", "DRIVERS", "ATTRS", "TAGS", "ENV", "CONST", "TAG", "TEST", "PROGRAM", "RESULT"}
ASSIGN_KEYS = {"NAME", "SYMLINK", "OWNER", "GROUP", "MODE", "SECLABEL", "ATTR", "SYSCTL", "ENV", "TAG", "RUN",
               "LABEL", "GOTO", "IMPORT", "OPTIONS"}
TOKEN = re.compile(r'\s*([A-Z_]+)(?:\{([^}]+)\})?\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*(,|$)')


def parse_rules(text: str) -> list[list[tuple[str, str | None, str, str]]]:
    rules = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        assert not line.endswith("\\"), f"line {number}: keep each rule on one line"
        tokens, pos = [], 0
        while pos < len(line):
            m = TOKEN.match(line, pos)
            assert m, f"line {number}: cannot parse at column {pos + 1}: {line[pos:pos + 30]!r}"
            key, attr, op, value, _ = m.groups()
            if op in ("==", "!="):
                assert key in MATCH_KEYS, f"line {number}: {key} is not a match key"
            else:
                assert key in ASSIGN_KEYS, f"line {number}: {key} cannot be assigned"
            assert (attr is not None) == (key in {"ATTR", "ATTRS", "ENV", "SYSCTL", "TEST", "IMPORT", "CONST"}), \
                f"line {number}: {key} {'needs' if attr is None else 'takes no'} {{attribute}}"
            tokens.append((key, attr, op, value))
            pos = m.end()
        rules.append(tokens)
    return rules


def udev_pattern_matches(pattern: str, name: str) -> bool:
    """udev's glob: shell patterns, alternatives separated by |."""
    return any(fnmatch.fnmatchcase(name, alt) for alt in pattern.split("|"))


def rule_for(rules, symlink):
    found = [r for r in rules if ("SYMLINK", None, "+=", symlink) in r]
    assert len(found) == 1, f"one rule must create /dev/{symlink}"
    return {(key, attr): (op, value) for key, attr, op, value in found[0]}


def test_udev_rules_parse_and_give_the_stable_names():
    rules = parse_rules(RULES.read_text())
    camera = rule_for(rules, "fluorosim/camera")
    assert camera[("SUBSYSTEM", None)] == ("==", "video4linux")
    assert udev_pattern_matches(camera[("KERNEL", None)][1], "video0")
    assert camera[("GROUP", None)] == ("=", "video")
    keypad = rule_for(rules, "fluorosim/keypad")
    assert keypad[("SUBSYSTEM", None)] == ("==", "input")
    assert udev_pattern_matches(keypad[("KERNEL", None)][1], "event3")
    assert not udev_pattern_matches(keypad[("KERNEL", None)][1], "mouse0"), "evdev event nodes only"
    assert keypad[("GROUP", None)] == ("=", "input")
    pedal = rule_for(rules, "fluorosim/pedal")
    assert pedal[("SUBSYSTEM", None)] == ("==", "tty")
    for name, expected in (("ttyUSB0", True), ("ttyACM12", True), ("ttyS0", False), ("tty1", False)):
        assert udev_pattern_matches(pedal[("KERNEL", None)][1], name) == expected, name
    assert pedal[("GROUP", None)] == ("=", "dialout")
    for rule in rules:
        modes = [value for key, _, op, value in rule if key == "MODE"]
        for mode in modes:
            assert int(mode, 8) & 0o007 == 0, "no access for other users"


def test_the_unit_admits_every_device_class_the_rules_name():
    s = unit_settings(UNIT.read_text())
    allowed = {v.split()[0] for v in s[("Service", "DeviceAllow")]}
    subsystem_to_device = {"video4linux": "char-video4linux", "input": "char-input", "tty": "char-ttyUSB",
                           "hidraw": "char-hidraw", "graphics": "/dev/fb0"}
    for rule in parse_rules(RULES.read_text()):
        subsystem = next(value for key, _, op, value in rule if key == "SUBSYSTEM")
        assert subsystem_to_device[subsystem] in allowed, subsystem
    groups = set(one(s, "Service", "SupplementaryGroups").split())
    for rule in parse_rules(RULES.read_text()):
        for key, _, _op, value in rule:
            if key == "GROUP":
                assert value in groups, f"the service is not in group {value}"


def test_rule_parser_rejects_mistakes():
    with pytest.raises(AssertionError, match="cannot parse"):
        parse_rules('SUBSYSTEM=="tty", KERNEL=ttyUSB*, SYMLINK+="x"')
    with pytest.raises(AssertionError, match="not a match key"):
        parse_rules('SUBSYTEM=="tty", SYMLINK+="x"')
    with pytest.raises(AssertionError, match="needs"):
        parse_rules('ATTRS=="03"')
