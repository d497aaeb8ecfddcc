"""xAPI statements of an ended session, a persistent queue for them, and the sender to an LRS.

Statements (xAPI 1.0.3): per task of each exercise run, the trainee (actor, an account on
the centre's system) `passed` or `failed` the task (object: an activity under the
exercise's), with a result holding success, the time to meet it and the task's metrics as
extensions; per exercise run one `completed` statement with the exercise's metrics. The
context names the appliance, the session and the case. Each statement's id is a UUID made
from the appliance, the session and the task, so queuing or sending it again can never
make a second copy: the LRS keeps one statement per id.

The statements wait in the ledger file's send queue (records.outbox, kind "xapi", one
destination "lrs"), beside the DICOM objects and outside the event chain: they survive
kill -9 and power loss, go out with backoff, and one confirmed is never handed out again.
The running appliance queues an ended session's statements and its send worker delivers
them (daemon.send_worker); `fluorosim lrs send` queues any ended session not yet queued and
sends at once, from the same queue.
"""

from __future__ import annotations

import base64
import json
import logging
import re
import sqlite3
import urllib.error
import urllib.request
import uuid
from pathlib import Path

from .. import __version__
from ..config.loading import resolve
from ..config.teaching import Lrs
from ..errors import FluorosimError
from ..records.export import iso
from ..records.outbox import FailureStreaks, Outbox, RoundReport

log = logging.getLogger(__name__)

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
#: The outbox's kind and the one destination of the statements.
KIND = "xapi"
DESTINATION = "lrs"


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


def statements(m: dict, lrs: Lrs) -> list[dict]:
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


def _label(s: dict, session_id: int) -> str:
    return f"xAPI '{s['verb']['display']['en']} {s['object']['definition']['name']['en']}' of session {session_id}"


def _marker(session_id: int) -> str:
    # Queued last, with no delivery: the session's statements are all in the queue.
    return f"session/{session_id}"


def queue_session(outbox: Outbox, conn: sqlite3.Connection, session_id: int, lrs: Lrs) -> int:
    """Queue the statements of ended session `session_id` for the LRS (kind "xapi", keyed by
    statement id); returns how many were new. Queuing a session again adds nothing."""
    from .metrics import session_metrics

    if outbox.has(_marker(session_id)):
        return 0        # queued before (an ended session's statements never change): spare the replay
    items = statements(session_metrics(conn, session_id), lrs)
    new = outbox.put_many([(st["id"], _label(st, session_id), json.dumps(st, sort_keys=True).encode()) for st in items],
                          [DESTINATION], session_id=session_id)
    outbox.put(_marker(session_id), f"xAPI statements of session {session_id} queued", b"", [], session_id=session_id)
    return new


def queue_ended_sessions(conn: sqlite3.Connection, outbox: Outbox, lrs: Lrs) -> int:
    """Queue the statements of every ended session of the ledger not queued before; returns how many sessions."""
    ended = [r[0] for r in conn.execute("SELECT id FROM sessions WHERE ended_wall IS NOT NULL ORDER BY id")]
    todo = [sid for sid in ended if not outbox.has(_marker(sid))]
    for sid in todo:
        queue_session(outbox, conn, sid, lrs)
    return len(todo)


def read_password(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8").strip()
    except OSError as e:
        raise FluorosimError(f"{path}: cannot read the LRS password ({e.strerror or e}); "
                             "check teaching.lrs.password_file in the appliance profile") from None


def _request(lrs: Lrs, password: str, method: str, url: str, body: bytes | None = None):
    auth = base64.b64encode(f"{lrs.username}:{password}".encode()).decode()
    req = urllib.request.Request(url, data=body, method=method, headers={
        "Authorization": f"Basic {auth}", "X-Experience-API-Version": XAPI_VERSION, "Content-Type": "application/json"})
    return urllib.request.urlopen(req, timeout=lrs.timeout_s)


def _statements_url(lrs: Lrs) -> str:
    return lrs.endpoint.rstrip("/") + "/statements"


class LrsError(Exception):
    """The LRS did not take a request: `str()` is the one line; `short` a few stable words for the banner."""

    def __init__(self, message: str, short: str):
        super().__init__(message)
        self.short = short


def _refusal(lrs: Lrs, e: Exception) -> LrsError:
    where = _statements_url(lrs)
    if isinstance(e, urllib.error.HTTPError):
        if e.code in (401, 403):
            why, short = (f"refused the credentials (HTTP {e.code}); check teaching.lrs.username and password_file",
                          "credentials refused")
        else:
            detail = e.read(300).decode("utf-8", "replace").strip().replace("\n", " ")
            why, short = f"answered HTTP {e.code} {e.reason}" + (f": {detail}" if detail else ""), f"HTTP {e.code}"
    else:
        reason = getattr(e, "reason", e)
        why, short = f"cannot be reached ({reason}); check teaching.lrs.endpoint and the network", str(reason)
    return LrsError(f"LRS {where} {why}", short)


def _post(lrs: Lrs, password: str, batch: list[dict]) -> None:
    """Store `batch` in the LRS; LrsError if it does not take it. A statement the LRS holds
    already (an earlier send whose answer was lost) counts as taken: a POST answered 409 is
    sent again one by one with PUT, which an LRS answers 204 (or 409) for a statement it holds."""
    try:
        with _request(lrs, password, "POST", _statements_url(lrs), json.dumps(batch).encode()) as response:
            response.read()
        return
    except urllib.error.HTTPError as e:
        if e.code != 409:
            raise _refusal(lrs, e) from None
    except (urllib.error.URLError, OSError) as e:
        raise _refusal(lrs, e) from None
    for st in batch:
        try:
            with _request(lrs, password, "PUT", f"{_statements_url(lrs)}?statementId={st['id']}",
                          json.dumps(st).encode()) as response:
                response.read()
        except urllib.error.HTTPError as e:
            if e.code != 409:
                raise _refusal(lrs, e) from None
        except (urllib.error.URLError, OSError) as e:
            raise _refusal(lrs, e) from None


class XapiSender:
    """Sends the queued statements (outbox kind "xapi") to the LRS of `lrs`; `profile` is the
    appliance profile's path (password_file is relative to it). A refusal or an unreachable LRS fails the batch,
    which waits with backoff (lrs.retry); after `retry.warn_after_failures` failed rounds in
    a row `problems()` gives the banner's words and one warning is logged."""

    def __init__(self, outbox: Outbox, lrs: Lrs, profile: Path, *, failures: dict[str, tuple[int, str]] | None = None):
        self.outbox, self.lrs, self.profile = outbox, lrs, profile
        self.streaks = FailureStreaks("xAPI", lrs.retry.warn_after_failures, log, failures)
        #: Kept across a reload, as the DICOM sender's.
        self.failures = self.streaks.counts

    def run_round(self, *, ignore_backoff: bool = False) -> RoundReport:
        """Send what is due, in batches of BATCH, until the queue is empty or the LRS fails."""
        report, retry = RoundReport(), self.lrs.retry
        while True:
            items = self.outbox.claim(DESTINATION, lease_s=self.lrs.timeout_s * (BATCH + 3), limit=BATCH,
                                      ignore_backoff=ignore_backoff)
            if not items:
                return report
            try:
                password = read_password(resolve(self.profile, self.lrs.password_file))
                _post(self.lrs, password, [json.loads(i.payload) for i in items])
            except (LrsError, FluorosimError) as e:
                message = f"{e}; {len(self.outbox.pending())} statement(s) kept in the queue for the next try"
                for item in items:
                    self.outbox.failed(item, str(e), first_delay_s=retry.first_delay_s, max_delay_s=retry.max_delay_s)
                report.errors.append(message)
                self.streaks.failed(DESTINATION, message, getattr(e, "short", "password file unreadable"))
                return report
            for item in items:
                self.outbox.delivered(item)
            report.sent[DESTINATION] = report.sent.get(DESTINATION, 0) + len(items)
            self.streaks.answered(DESTINATION)

    def problems(self) -> list[str]:
        return self.streaks.problems()
