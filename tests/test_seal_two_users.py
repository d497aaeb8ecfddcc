"""Privilege separation of the ledger's seal, with two real users.

The helper (`fluorosim seal serve`) runs as root, as fluorosim-seal.service does; the writer runs
as a throwaway system user made for the test, as fluorosim.service runs as `fluorosim`. The
layout is the one provisioning makes: the key 0400 in a 0700 root folder, the anchor in a root
folder anyone may read, the socket root-owned with the service's group and mode 0660 (what
fluorosim-seal.socket's SocketGroup= and SocketMode= give), the ledger in the service user's
own state folder.

The service user's attempts are the ones a person with its shell would make; the verdicts are
read as root afterwards with `fluorosim logs verify`, not from what the user's process says.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest

from appliance.cli import main
from appliance.records.seal import make_key

REPO = Path(__file__).resolve().parents[1]
TOOLS = [t for t in ("useradd", "userdel", "setpriv") if shutil.which(t) is None]
pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="needs root to create a throwaway system user and run as it"),
    pytest.mark.skipif(bool(TOOLS), reason=f"needs {', '.join(TOOLS)} (Debian packages passwd, util-linux)"),
]

#: What the service user tries, each attempt reported as what happened (run as that user).
SERVICE_USER = textwrap.dedent("""
    import hashlib, hmac, json, os, sqlite3, sys
    from pathlib import Path
    from appliance.console.state import ConsoleEvent
    from appliance.errors import FluorosimError
    from appliance.records.ledger import EVENT_COLUMNS, GENESIS, Ledger, event_hash
    from appliance.records.seal import HelperSeal

    key, anchor, sock, ledger, step = sys.argv[1:6]
    seen = {}
    def attempt(name, action):
        try:
            action()
            seen[name] = "done"
        except PermissionError:
            seen[name] = "permission denied"
        except FluorosimError as e:
            seen[name] = str(e)

    def record():
        with Ledger(ledger, seal=HelperSeal(Path(sock))) as led:
            led.start_session("Dr A", "case", "C-arm", t_wall=1_700_000_000.0, t_monotonic=0.0)
            led.record([ConsoleEvent(1.0, "fluoro_on", {"mode": "continuous"}),
                        ConsoleEvent(61.0, "fluoro_off", {"run": 1, "reason": "released", "start_t": 1.0,
                                                          "duration_s": 60.0, "air_kerma_mgy": 4.0, "dap_gy_cm2": 0.4,
                                                          "pulses": 0, "mode": "continuous", "zoom": 1},
                                     60.0, 4.0, 0.4, 60.0, 4.0, 0.4)])
            led.end_session(t_wall=1_700_000_100.0)

    def forge_anchor():      # name an earlier, smaller ledger as the newest authenticated entry
        doc = json.loads(Path(anchor).read_text())
        Path(anchor).write_text(json.dumps({**doc, "count": 1}))

    def replace_anchor():    # or swap the file for one of its own
        mine = Path(ledger).with_name("anchor.json")
        mine.write_text("{}")
        os.replace(mine, anchor)

    def halve_and_reseal():  # halve the kerma, recompute every link, sign with a key of its own
        conn = sqlite3.connect(ledger)
        conn.row_factory = sqlite3.Row
        conn.execute("UPDATE events SET air_kerma_mgy = air_kerma_mgy / 2, d_air_kerma_mgy = d_air_kerma_mgy / 2")
        conn.execute("UPDATE events SET detail = json_set(detail, '$.air_kerma_mgy', "
                     "json_extract(detail, '$.air_kerma_mgy') / 2) WHERE kind IN ('session_end', 'fluoro_off')")
        conn.execute("UPDATE sessions SET air_kerma_mgy = air_kerma_mgy / 2")
        own_key, prev, prev_mac = os.urandom(32), GENESIS, ""
        for r in [dict(r) for r in conn.execute(f"SELECT {', '.join(EVENT_COLUMNS)} FROM events ORDER BY id")]:
            r["prev_hash"] = prev
            r["hash"] = event_hash(prev, r)
            mac = hmac.new(own_key, f"{r['id']}|{prev_mac}|{r['hash']}".encode(), hashlib.sha256).hexdigest()
            conn.execute("UPDATE events SET prev_hash = ?, hash = ?, mac = ? WHERE id = ?",
                         (r["prev_hash"], r["hash"], mac, r["id"]))
            prev, prev_mac = r["hash"], mac
        conn.commit()

    def resign_history():    # ask the helper itself for the MAC of an entry it has anchored
        HelperSeal(Path(sock)).mac(1, "", "0" * 64)

    if step == "record":
        attempt("read the key", lambda: Path(key).read_bytes())
        attempt("record a session through the helper", record)
    else:
        attempt("rewrite the anchor", forge_anchor)
        attempt("replace the anchor", replace_anchor)
        attempt("ask the helper to re-sign history", resign_history)
        attempt("halve the kerma and re-seal with its own key", halve_and_reseal)
    print(json.dumps(seen))
""")


@pytest.fixture
def service_user():
    name = f"fluorosim-t{secrets.token_hex(3)}"
    subprocess.run(["useradd", "--system", "--user-group", "--no-create-home", "--shell", "/usr/sbin/nologin", name],
                   check=True, capture_output=True)
    try:
        yield name, int(subprocess.check_output(["id", "-u", name])), int(subprocess.check_output(["id", "-g", name]))
    finally:
        subprocess.run(["userdel", name], check=False, capture_output=True)
        subprocess.run(["groupdel", name], check=False, capture_output=True)


@pytest.fixture
def layout(service_user):
    """Folders as provisioning makes them, under a top folder every user may enter."""
    _, uid, gid = service_user
    top = Path(tempfile.mkdtemp(prefix="fluorosim-seal-"))
    top.chmod(0o755)
    paths = {"key_dir": top / "etc-fluorosim-seal", "anchor_dir": top / "var-lib-fluorosim-seal",
             "state": top / "var-lib-fluorosim", "run": top / "run"}
    for p in paths.values():
        p.mkdir()
    paths["key_dir"].chmod(0o700)
    paths["state"].chmod(0o700)
    os.chown(paths["state"], uid, gid)
    (top / "service_user.py").write_text(SERVICE_USER)
    try:
        yield top, {"key": paths["key_dir"] / "ledger.key", "anchor": paths["anchor_dir"] / "anchor.json",
                    "sock": paths["run"] / "seal.sock", "ledger": paths["state"] / "ledger.sqlite"}
    finally:
        shutil.rmtree(top, ignore_errors=True)


def verify_as_root(ledger: Path, f: dict, monkeypatch, capsys) -> tuple[int, str]:
    """`fluorosim logs verify` as root, with the key, as the auditor runs it."""
    monkeypatch.setenv("FLUOROSIM_SEAL_KEY", str(f["key"]))
    monkeypatch.setenv("FLUOROSIM_SEAL_ANCHOR", str(f["anchor"]))
    capsys.readouterr()
    rc = main(["logs", "verify", "--ledger", str(ledger)])
    out = capsys.readouterr()
    return rc, out.out + out.err


def as_service_user(user, top: Path, f: dict, step: str) -> dict:
    _, uid, gid = user
    result = subprocess.run(["setpriv", f"--reuid={uid}", f"--regid={gid}", "--clear-groups", sys.executable,
                             str(top / "service_user.py"), str(f["key"]), str(f["anchor"]), str(f["sock"]),
                             str(f["ledger"]), step],
                            cwd=REPO, capture_output=True, text=True, timeout=60,
                            env={**os.environ, "PYTHONPATH": str(REPO), "HOME": str(f["ledger"].parent)})
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_the_service_user_cannot_read_the_key_nor_forge_what_the_helper_anchored(service_user, layout, monkeypatch,
                                                                                 capsys):
    top, f = layout
    _, _, gid = service_user
    make_key(f["key"])
    helper = subprocess.Popen([sys.executable, "-m", "appliance", "seal", "serve", "--key", str(f["key"]),
                               "--anchor", str(f["anchor"]), "--ledger", str(f["ledger"]), "--socket", str(f["sock"])],
                              cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60        # a loaded two-core machine takes seconds to start Python
        while not f["sock"].exists() and time.monotonic() < deadline and helper.poll() is None:
            time.sleep(0.05)
        assert f["sock"].exists(), helper.stderr.read() if helper.poll() is not None else "the helper made no socket"
        os.chown(f["sock"], 0, gid)                 # SocketGroup=fluorosim

        seen = as_service_user(service_user, top, f, "record")
        assert seen == {"read the key": "permission denied", "record a session through the helper": "done"}
        rc, said = verify_as_root(f["ledger"], f, monkeypatch, capsys)
        assert rc == 0, said
        conn = sqlite3.connect(f"file:{f['ledger']}?mode=ro", uri=True)
        newest = conn.execute("SELECT id, hash FROM events ORDER BY id DESC LIMIT 1").fetchone()
        conn.close()
        anchor = json.loads(f["anchor"].read_text())
        # start, fluoro_on, fluoro_off, session_end: 4 events, the last anchored by the helper.
        assert (anchor["count"], anchor["hash"]) == (4, newest[1]) and newest[0] == 4
        assert f["anchor"].stat().st_uid == 0

        seen = as_service_user(service_user, top, f, "forge")
        assert seen["rewrite the anchor"] == "permission denied"
        assert seen["replace the anchor"] == "permission denied"
        assert "already anchored" in seen["ask the helper to re-sign history"]
        assert seen["halve the kerma and re-seal with its own key"] == "done"   # it owns the file...
        assert json.loads(f["anchor"].read_text()) == anchor
        rc, said = verify_as_root(f["ledger"], f, monkeypatch, capsys)
        assert rc == 1 and "NOT INTACT" in said and "MAC does not match" in said    # ...and it shows
    finally:
        helper.terminate()
        helper.wait(10)
