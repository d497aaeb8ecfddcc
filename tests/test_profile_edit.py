"""`fluorosim profile edit` and the atomic replacement under it."""

import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from unittest import mock

import pytest
from in_process_cli import Result, fluorosim

from appliance.atomic_file import write_atomic
from appliance.config import FluoroscopeProfile, load_profile
from appliance.errors import FluorosimError

REPO = Path(__file__).resolve().parents[1]


def editor_script(tmp_path: Path, *edits: tuple[str, str]) -> str:
    """An $EDITOR that applies the n-th (old, new) replacement on its n-th run."""
    counter = tmp_path / "runs"
    script = tmp_path / "editor.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        from pathlib import Path
        edits = {list(edits)!r}
        counter = Path({str(counter)!r})
        n = int(counter.read_text()) if counter.exists() else 0
        counter.write_text(str(n + 1))
        old, new = edits[min(n, len(edits) - 1)]
        p = Path(sys.argv[1])
        p.write_text(p.read_text().replace(old, new, 1))
    """))
    return f"{sys.executable} {script}"


def run_edit(path: Path, editor: str, answers: str = "") -> Result:
    """`fluorosim profile edit PATH` in this process (the editor is still a real child process), with
    `answers` typed at its prompt: what is under test is the command, not a new interpreter."""
    with mock.patch.dict(os.environ, EDITOR=editor, VISUAL=""):
        return fluorosim("profile", "edit", path, cwd=REPO, stdin=answers)


def test_valid_edit_replaces_file_and_keeps_backup(config_copy, tmp_path):
    path = config_copy / "fluoroscopes" / "generic-ii-carm.yaml"
    before = path.read_text()
    result = run_edit(path, editor_script(tmp_path, ("kvp: 75", "kvp: 90")))
    assert result.returncode == 0, result.stderr
    assert load_profile(path, FluoroscopeProfile).tube.kvp == 90
    assert (path.parent / (path.name + ".bak")).read_text() == before
    assert "# A generic mobile C-arm" in path.read_text(), "comments must survive an edit"
    assert not list(path.parent.glob(".*edit-*")), "the editing copy must be removed"


def test_invalid_edit_can_be_abandoned_and_leaves_file_untouched(config_copy, tmp_path):
    path = config_copy / "fluoroscopes" / "generic-ii-carm.yaml"
    before = path.read_bytes()
    result = run_edit(path, editor_script(tmp_path, ("kvp: 75", "kvp: 9000")), answers="a\n")
    assert result.returncode == 2
    assert f"{path.name}:" in result.stderr and "tube.kvp" in result.stderr
    assert "Traceback" not in result.stderr
    assert path.read_bytes() == before
    assert not (path.parent / (path.name + ".bak")).exists()


def test_invalid_edit_can_be_edited_again(config_copy, tmp_path):
    path = config_copy / "fluoroscopes" / "generic-ii-carm.yaml"
    editor = editor_script(tmp_path, ("kvp: 75", "kvp: 9000"), ("kvp: 9000", "kvp: 81"))
    result = run_edit(path, editor, answers="e\n")
    assert result.returncode == 0, result.stderr
    assert load_profile(path, FluoroscopeProfile).tube.kvp == 81


def test_cross_file_problem_is_caught_before_saving(config_copy, tmp_path):
    path = config_copy / "appliance.yaml"
    before = path.read_bytes()
    result = run_edit(path, editor_script(tmp_path, ("cases/child-torso-vcug.yaml", "cases/missing.yaml")), answers="a\n")
    assert result.returncode == 2 and "missing.yaml does not exist" in result.stderr
    assert path.read_bytes() == before


def test_write_atomic_refuses_overwrite_when_asked(tmp_path):
    target = tmp_path / "x.csv"
    target.write_text("old")
    with pytest.raises(FluorosimError, match="refusing to overwrite"):
        write_atomic(target, b"new", overwrite=False)
    assert target.read_text() == "old"


def test_write_atomic_into_missing_folder_is_one_clear_error(tmp_path):
    with pytest.raises(FluorosimError, match="cannot write"):
        write_atomic(tmp_path / "no" / "such" / "x.yaml", b"data")


WRITER = """
import sys
from appliance.atomic_file import write_atomic
a, b = open(sys.argv[2], 'rb').read(), open(sys.argv[3], 'rb').read()
print('ready', flush=True)
i = 0
while True:
    write_atomic(sys.argv[1], a if i % 2 else b, backup=True)
    i += 1
"""


def test_kill_during_atomic_writes_never_leaves_a_partial_profile(tmp_path):
    """SIGKILL a writer that keeps replacing a profile, at random moments: the file is always one whole version."""
    old = (REPO / "configs" / "fluoroscopes" / "generic-ii-carm.yaml").read_bytes()
    new = old.replace(b"kvp: 75", b"kvp: 90") * 20  # a larger version, so a torn write would show
    (tmp_path / "a").write_bytes(old)
    (tmp_path / "b").write_bytes(new)
    target = tmp_path / "profile.yaml"
    target.write_bytes(old)
    rng = random.Random(1)
    for _ in range(25):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target), str(tmp_path / "a"), str(tmp_path / "b")],
                                cwd=REPO, stdout=subprocess.PIPE)
        assert proc.stdout.readline().strip() == b"ready"
        time.sleep(rng.uniform(0.0, 0.03))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert target.read_bytes() in (old, new)
        bak = target.with_name(target.name + ".bak")
        if bak.exists():
            assert bak.read_bytes() in (old, new)
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    # A kill between mkstemp and rename may leave a hidden temporary file; never a damaged profile.
    assert all(name.endswith(".tmp") for name in leftovers), leftovers


def test_an_editor_that_does_not_exist_is_one_line_and_the_profile_untouched(config_copy, tmp_path):
    path = config_copy / "fluoroscopes" / "generic-ii-carm.yaml"
    before = path.read_bytes()
    result = run_edit(path, "no-such-editor-here --wait")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "EDITOR=no-such-editor-here --wait: no such program" in lines[0]
    assert path.read_bytes() == before and not list(path.parent.glob(".*edit-*"))


def test_no_editor_named_and_no_terminal_is_one_line_not_a_hang(config_copy):
    """With EDITOR and VISUAL empty the fallbacks are terminal editors (vi waited forever on a pipe)."""
    path = config_copy / "fluoroscopes" / "generic-ii-carm.yaml"
    before = path.read_bytes()
    start = time.monotonic()
    result = run_edit(path, "")
    assert time.monotonic() - start < 10
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "EDITOR is not set and standard input is not a terminal" in lines[0]
    assert path.read_bytes() == before and not list(path.parent.glob(".*edit-*"))
