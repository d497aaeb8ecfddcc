"""xAPI statements of an ended session, a persistent queue for them, and the sender to an LRS.

Statements (xAPI 1.0.3): per task of each exercise run, the trainee (actor, an account on
the centre's system) `passed` or `failed` the task (object: an activity under the
exercise's), with a result holding success, the time to meet it and the task's metrics as
extensions; per exercise run one `completed` statement with the exercise's metrics. The
context names the appliance, the session and the case. Each statement's id is a UUID made
from the appliance, the session and the task, so queuing or sending it again can never
make a second copy: the LRS keeps one statement per id.

The queue is its own SQLite file (xapi-outbox.sqlite beside the ledger), not the ledger:
the ledger stays the one record of what happened, the queue only what is still to send.
It sits behind `put` / `pending` / `sent` / `failed`, the interface a shared outbox of the
DICOM sends can take over.
"""

from __future__ import annotations

import base64
import json
import re
import sqlite3
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

from .. import __version__
from ..errors import FluorosimError
from ..records.export import iso

XAPI_VERSION = "1.0.3"
VERB_PASSED = "http://adlnet.gov/expapi/verbs/passed"
VERB_FAILED = "http://adlnet.gov/expapi/verbs/failed"
VERB_COMPLETED = "http://adlnet.gov/expapi/verbs/completed"
ACTIVITY_TYPE_ASSESSMENT = "http://adlnet.gov/expapi/activities/assessment"
ACTIVITY_TYPE_SIMULATION = "http://adlnet.gov/expapi/activities/simulation"
#: Namespace of the statement ids (a fixed UUID: ids stay stable across versions).
ID_NAMESPACE = uuid.UUID("5b0f3f0e-8a53-4c6e-9a55-0f1a0e5c7d21")
#: Statements sent in one request.
BATCH = 50


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "x"


def _duration(seconds: float | None) -> str | None:
    return None if seconds is None else f"PT{max(seconds, 0.0):.2f}S"


def _extensions(metrics: dict) -> dict:
    out = {}
    for key, value in metrics.items():
        if isinstance(value, (int, float)) and not isinstance(value, bool) or isinstance(value, dict):
            out[f"urn:fluorosim:metric:{key}"] = value
    return out


def statements(m: dict, lrs) -> list[dict]:
    """The statements of one session's metrics (`metrics.session_metrics`) for LRS profile `lrs`."""
    info = m["session"]
    actor = {"objectType": "Agent", "name": info["trainee"],
             "account": {"homePage": lrs.account_home_page, "name": info["trainee"]}}
    when = iso(info["ended_wall"] or info["started_wall"])
    context_ext = {"urn:fluorosim:appliance": lrs.appliance_id, "urn:fluorosim:session": info["id"],
                   "urn:fluorosim:case": info["case"], "urn:fluorosim:fluoroscope": info["fluoroscope"],
                   "urn:fluorosim:version": __version__}
    out = []
    for i, ex in enumerate(m["exercises"]):
        ex_id = f"urn:fluorosim:exercise:{_slug(ex['title'])}"
        ex_activity = {"objectType": "Activity", "id": ex_id,
                       "definition": {"name": {"en": ex["title"]}, "type": ACTIVITY_TYPE_SIMULATION}}
        context = {"platform": "fluorosim", "extensions": context_ext}
        for j, task in enumerate(ex["tasks"]):
            met = task["state"] == "met"
            out.append({
                "id": str(uuid.uuid5(ID_NAMESPACE, f"{lrs.appliance_id}/{info['id']}/{i}/{j}")),
                "actor": actor,
                "verb": {"id": VERB_PASSED if met else VERB_FAILED, "display": {"en": "passed" if met else "failed"}},
                "object": {"objectType": "Activity", "id": f"{ex_id}:task:{_slug(task['name'])}",
                           "definition": {"name": {"en": task["name"]}, "type": ACTIVITY_TYPE_ASSESSMENT}},
                "result": {"success": met, "completion": task["state"] in ("met", "skipped"),
                           **({"duration": _duration(task["time_to_met_s"])} if met else {}),
                           "extensions": {**_extensions(task["metrics"]), "urn:fluorosim:task-state": task["state"]}},
                "context": {**context, "contextActivities": {"parent": [{"objectType": "Activity", "id": ex_id}]}},
                "timestamp": when,
            })
        duration = None if ex["ended_s"] is None else ex["ended_s"] - ex["started_s"]
        out.append({
            "id": str(uuid.uuid5(ID_NAMESPACE, f"{lrs.appliance_id}/{info['id']}/{i}")),
            "actor": actor, "verb": {"id": VERB_COMPLETED, "display": {"en": "completed"}}, "object": ex_activity,
            "result": {"completion": True, "success": ex["metrics"]["tasks_met"] == len(ex["tasks"]),
                       "score": {"raw": ex["metrics"]["tasks_met"], "min": 0, "max": len(ex["tasks"])},
                       **({"duration": _duration(duration)} if duration is not None else {}),
                       "extensions": _extensions(ex["metrics"])},
            "context": context, "timestamp": when,
        })
    return out


class XapiQueue:
    """Statements waiting for the LRS, kept on disk until it has taken them (SQLite, WAL, FULL sync)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            self._conn.execute("PRAGMA journal_mode = WAL")
            self._conn.execute("PRAGMA synchronous = FULL")
            self._conn.execute("PRAGMA busy_timeout = 5000")
            self._conn.execute("CREATE TABLE IF NOT EXISTS statements (id TEXT PRIMARY KEY, session_id INTEGER NOT NULL, "
                               "body TEXT NOT NULL, queued_wall REAL NOT NULL, attempts INTEGER NOT NULL DEFAULT 0, "
                               "last_error TEXT, sent_wall REAL)")
            self._conn.execute("CREATE TABLE IF NOT EXISTS sessions (session_id INTEGER PRIMARY KEY, queued_wall REAL NOT NULL)")
        except (sqlite3.Error, OSError) as e:
            raise FluorosimError(f"{self.path}: cannot open the xAPI queue ({e}); check the data folder") from None

    def put(self, session_id: int, items: list[dict]) -> int:
        """Queue a session's statements, all or none; one already queued (same id) is not queued
        again. Returns how many were new."""
        with self._conn:
            before = self._conn.total_changes
            self._conn.executemany("INSERT OR IGNORE INTO statements (id, session_id, body, queued_wall) VALUES (?, ?, ?, ?)",
                                   [(s["id"], session_id, json.dumps(s, sort_keys=True), time.time()) for s in items])
            new = self._conn.total_changes - before
            self._conn.execute("INSERT OR IGNORE INTO sessions (session_id, queued_wall) VALUES (?, ?)", (session_id, time.time()))
            return new

    def queued_sessions(self) -> set[int]:
        return {r[0] for r in self._conn.execute("SELECT session_id FROM sessions")}

    def pending(self, limit: int = BATCH) -> list[dict]:
        rows = self._conn.execute("SELECT body FROM statements WHERE sent_wall IS NULL ORDER BY rowid LIMIT ?", (limit,))
        return [json.loads(r[0]) for r in rows]

    def count_pending(self) -> int:
        return self._conn.execute("SELECT count(*) FROM statements WHERE sent_wall IS NULL").fetchone()[0]

    def sent(self, ids: list[str]) -> None:
        with self._conn:
            self._conn.executemany("UPDATE statements SET sent_wall = ?, last_error = NULL WHERE id = ?",
                                   [(time.time(), i) for i in ids])

    def failed(self, ids: list[str], error: str) -> None:
        with self._conn:
            self._conn.executemany("UPDATE statements SET attempts = attempts + 1, last_error = ? WHERE id = ?",
                                   [(error, i) for i in ids])

    def close(self) -> None:
        self._conn.close()


def read_password(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8").strip()
    except OSError as e:
        raise FluorosimError(f"{path}: cannot read the LRS password ({e.strerror or e}); "
                             "check teaching.lrs.password_file in the appliance profile") from None


def _request(lrs, password: str, method: str, url: str, body: bytes | None = None):
    auth = base64.b64encode(f"{lrs.username}:{password}".encode()).decode()
    req = urllib.request.Request(url, data=body, method=method, headers={
        "Authorization": f"Basic {auth}", "X-Experience-API-Version": XAPI_VERSION, "Content-Type": "application/json"})
    return urllib.request.urlopen(req, timeout=lrs.timeout_s)


def _statements_url(lrs) -> str:
    return lrs.endpoint.rstrip("/") + "/statements"


def _refusal(lrs, e: Exception, kept: int) -> FluorosimError:
    where = _statements_url(lrs)
    if isinstance(e, urllib.error.HTTPError):
        if e.code in (401, 403):
            why = f"refused the credentials (HTTP {e.code}); check teaching.lrs.username and password_file"
        else:
            detail = e.read(300).decode("utf-8", "replace").strip().replace("\n", " ")
            why = f"answered HTTP {e.code} {e.reason}" + (f": {detail}" if detail else "")
    else:
        reason = getattr(e, "reason", e)
        why = f"cannot be reached ({reason}); check teaching.lrs.endpoint and the network"
    return FluorosimError(f"LRS {where} {why}; {kept} statement(s) kept in the queue for the next try")


def send_pending(queue: XapiQueue, lrs, password: str) -> int:
    """Send what is queued, in batches; returns how many the LRS took. On a refusal or a network
    failure nothing is lost: the statements stay queued and FluorosimError says why in one line."""
    total = 0
    while True:
        batch = queue.pending()
        if not batch:
            return total
        ids = [s["id"] for s in batch]
        try:
            with _request(lrs, password, "POST", _statements_url(lrs), json.dumps(batch).encode()) as response:
                response.read()
            queue.sent(ids)
            total += len(ids)
            continue
        except urllib.error.HTTPError as e:
            if e.code != 409:
                queue.failed(ids, f"HTTP {e.code}")
                raise _refusal(lrs, e, queue.count_pending()) from None
        except (urllib.error.URLError, OSError) as e:
            queue.failed(ids, str(getattr(e, "reason", e)))
            raise _refusal(lrs, e, queue.count_pending()) from None
        # 409: some of the batch is already in the LRS (an earlier send whose answer was lost);
        # one by one, with PUT, which an LRS answers 204 for a statement it holds already.
        for s in batch:
            try:
                with _request(lrs, password, "PUT", f"{_statements_url(lrs)}?statementId={s['id']}",
                              json.dumps(s).encode()) as response:
                    response.read()
            except urllib.error.HTTPError as e:
                if e.code != 409:
                    queue.failed([s["id"]], f"HTTP {e.code}")
                    raise _refusal(lrs, e, queue.count_pending()) from None
            except (urllib.error.URLError, OSError) as e:
                queue.failed([s["id"]], str(getattr(e, "reason", e)))
                raise _refusal(lrs, e, queue.count_pending()) from None
            queue.sent([s["id"]])
            total += 1


def queue_ended_sessions(conn: sqlite3.Connection, queue: XapiQueue, lrs) -> int:
    """Queue the statements of every ended session of the ledger not queued before; returns how many sessions."""
    from .metrics import session_metrics

    done = queue.queued_sessions()
    ended = [r[0] for r in conn.execute("SELECT id FROM sessions WHERE ended_wall IS NOT NULL ORDER BY id")]
    todo = [sid for sid in ended if sid not in done]
    for sid in todo:
        queue.put(sid, statements(session_metrics(conn, sid), lrs))
    return len(todo)
