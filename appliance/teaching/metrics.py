"""Metrics of a session, of each exercise run in it and of each task, from the ledger alone.

What is counted (times on the console's clock, s; doses as the console recorded them):

- exposures: presses of the pedal or fluoro key (a run split by a settings change while
  exposing is still one exposure); blank exposures: those during an exercise in which no
  recorded image showed any part of a target (the task's, or for a whole exercise any of
  its tasks'); an exposure with no tracked image at all is blank too;
- fluoroscopy time, K_a,r and DAP: the sums of the events' increments in the scope, so the
  session's equal the ledger's totals;
- images saved, on target (some of the current task's target in the field) and off
  target; saves of a held image (last-image-hold);
- collimated share: exposure time with the blades in on either axis over all exposure
  time; mean field area at the reference point, weighted by exposure time; exposure time
  per zoom level; pulsed share: exposure time in a pulsed mode over all;
- time to the first on-target image: from the start of the task (or exercise) to the first
  recorded image that showed the current task's target;
- tasks met, skipped or not done, replayed through the same ExerciseProgress the live
  screen used.
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field

from pydantic import ValidationError

from ..config.exercise import ExerciseProfile
from ..errors import FluorosimError
from .progress import ExerciseProgress
from .views import Beam, shows

#: Ledger event kinds this package writes (through Console.note), besides the console's own.
NOTE_KINDS = ("trainee", "exercise_start", "task_skip", "task_met", "exercise_end", "view", "save_view")


@dataclass
class Exposure:
    start_t: float
    end_t: float | None = None
    beams: list[Beam] = field(default_factory=list)
    scopes: list[Scope] = field(default_factory=list)


@dataclass
class Scope:
    """What is summed over one span: the session, one exercise run, or one task."""

    targets: list = field(default_factory=list)     # Target models judged for blank exposures
    fluoro_time_s: float = 0.0
    air_kerma_mgy: float = 0.0
    dap_gy_cm2: float = 0.0
    exposures: list[Exposure] = field(default_factory=list)
    run_time_s: float = 0.0
    collimated_s: float = 0.0
    area_time: float = 0.0
    pulsed_s: float = 0.0
    zoom_s: dict = field(default_factory=lambda: {1: 0.0, 2: 0.0, 3: 0.0, 4: 0.0})
    saves: int = 0
    held_saves: int = 0
    on_target: int = 0
    off_target: int = 0
    first_on_target_t: float | None = None
    start_t: float | None = None

    def add_run(self, d: dict) -> None:
        dur = float(d.get("duration_s", 0.0))
        self.run_time_s += dur
        fov = d.get("fov_mm")
        if fov is not None and min(d.get("collimation_h_mm", fov), d.get("collimation_v_mm", fov)) < fov - 1e-9:
            self.collimated_s += dur
        self.area_time += dur * float(d.get("field_area_cm2", 0.0))
        if d.get("pulse_rate_per_s"):
            self.pulsed_s += dur
        z = int(d.get("zoom", 1))
        self.zoom_s[z] = self.zoom_s.get(z, 0.0) + dur

    def figures(self) -> dict:
        judged = [e for e in self.exposures if self.targets]
        blank = sum(1 for e in judged if not any(shows(b, t) for b in e.beams for t in self.targets))
        rt = self.run_time_s
        return {
            "exposures": len(self.exposures),
            "blank_exposures": blank if self.targets else None,
            "fluoro_time_s": self.fluoro_time_s,
            "air_kerma_mgy": self.air_kerma_mgy,
            "dap_gy_cm2": self.dap_gy_cm2,
            "images_saved": self.saves,
            "images_on_target": self.on_target if self.targets else None,
            "images_off_target": self.off_target if self.targets else None,
            "held_image_saves": self.held_saves,
            "collimated_share": self.collimated_s / rt if rt > 0 else None,
            "mean_field_area_cm2": self.area_time / rt if rt > 0 else None,
            "zoom_time_s": {str(k): v for k, v in sorted(self.zoom_s.items())},
            "pulsed_share": self.pulsed_s / rt if rt > 0 else None,
            "time_to_first_on_target_s": (None if self.first_on_target_t is None or self.start_t is None
                                          else self.first_on_target_t - self.start_t),
        }


def session_row(conn: sqlite3.Connection, session_id: int) -> dict:
    row = conn.execute("SELECT * FROM sessions WHERE id = ?", (session_id,)).fetchone()
    if row is None:
        last = conn.execute("SELECT max(id) FROM sessions").fetchone()[0]
        raise FluorosimError(f"no session {session_id} in the ledger" +
                             (f" (sessions 1..{last}; `fluorosim logs list` shows them)" if last else " (it has none yet)"))
    return dict(row)


def session_events(conn: sqlite3.Connection, session_id: int) -> list[dict]:
    out = []
    for r in conn.execute("SELECT id, t_wall, t_monotonic, kind, fluoro_time_s, air_kerma_mgy, dap_gy_cm2, d_fluoro_time_s, "
                          "d_air_kerma_mgy, d_dap_gy_cm2, detail FROM events WHERE session_id = ? ORDER BY id", (session_id,)):
        e = dict(r)
        e["detail"] = json.loads(e["detail"])
        out.append(e)
    return out


def trainee_of(events: list[dict], default: str) -> str:
    names = [e["detail"].get("name") for e in events if e["kind"] == "trainee"]
    return names[-1] if names else default


def _event_t(e: dict, last_t: float) -> float:
    # session_end carries no console time: it happens after the last event.
    return last_t if e["t_monotonic"] is None else float(e["t_monotonic"])


def session_metrics(conn: sqlite3.Connection, session_id: int) -> dict:
    """Everything a report shows about one session, as plain data (JSON-ready)."""
    session = session_row(conn, session_id)
    events = session_events(conn, session_id)
    whole = Scope()
    runs: list[dict] = []       # one per exercise run: progress, scope, task scopes
    live: dict | None = None    # the exercise run in progress
    exposures: list[Exposure] = []
    open_exposure: Exposure | None = None
    save_kinds: dict[int, str] = {}
    series: dict[str, list[float]] = {"t": [], "air_kerma_mgy": [], "dap_gy_cm2": [], "fluoro_time_s": []}
    saves_out = []
    t = 0.0
    t0 = events[0]["t_monotonic"] if events and events[0]["t_monotonic"] is not None else 0.0
    whole.start_t = t0

    def scopes() -> list[Scope]:
        if live is None:
            return [whole]
        task = live["progress"].current
        return [whole, live["scope"]] + ([live["tasks"][task.index]] if task is not None else [])

    def close_live(t_end: float) -> None:
        nonlocal live
        if live is not None:
            live["progress"].end(t_end)
            live = None

    for e in events:
        t = _event_t(e, t)
        d = e["detail"]
        kind = e["kind"]
        here = scopes()
        for s in here:
            s.fluoro_time_s += e["d_fluoro_time_s"]
            s.air_kerma_mgy += e["d_air_kerma_mgy"]
            s.dap_gy_cm2 += e["d_dap_gy_cm2"]
        if e["d_fluoro_time_s"] or e["d_air_kerma_mgy"] or kind in ("fluoro_on", "fluoro_off", "session_start"):
            series["t"].append(t - t0)
            series["air_kerma_mgy"].append(e["air_kerma_mgy"])
            series["dap_gy_cm2"].append(e["dap_gy_cm2"])
            series["fluoro_time_s"].append(e["fluoro_time_s"])
        if kind == "fluoro_on" and d.get("reason") == "pressed":
            open_exposure = Exposure(t, scopes=here)
            exposures.append(open_exposure)
            for s in here:
                s.exposures.append(open_exposure)
        elif kind == "fluoro_off":
            for s in here:
                s.add_run(d)
            if open_exposure is not None and d.get("reason") not in ("settings changed", "profile reloaded"):
                open_exposure.end_t = t
                open_exposure = None
        elif kind == "view":
            beam = Beam.of(d)
            if open_exposure is not None:
                open_exposure.beams.append(beam)
            if live is not None and live["progress"].current is not None:
                task = live["progress"].current
                target = live["exercise"].tasks[task.index].target
                if shows(beam, target):
                    for s in (live["scope"], live["tasks"][task.index]):
                        if s.first_on_target_t is None:
                            s.first_on_target_t = t
        elif kind == "save":
            save_kinds[int(d.get("n", 0))] = d.get("image", "live")
            for s in here:
                s.saves += 1
                s.held_saves += d.get("image") == "held"
        elif kind == "save_view":
            n = int(d.get("n", 0))
            saved = Beam.of(d["view"]) if d.get("view") else None
            if saved is not None and open_exposure is not None:
                open_exposure.beams.append(saved)
            verdict = None
            task_name = None
            if live is not None and live["progress"].current is not None:
                task = live["progress"].current
                task_name = task.name
                target = live["exercise"].tasks[task.index].target
                on = saved is not None and shows(saved, target)
                for s in here[1:]:
                    if on:
                        s.on_target += 1
                    else:
                        s.off_target += 1
                if on:
                    whole.on_target += 1
                else:
                    whole.off_target += 1
                verdict = live["progress"].save(t, n, saved)
            saves_out.append({"n": n, "t_s": t - t0, "image": save_kinds.get(n, "live"), "task": task_name,
                              "verdict": None if verdict is None else verdict.as_dict(), "tracked": saved is not None})
        elif kind == "exercise_start":
            close_live(t)
            try:
                exercise = ExerciseProfile.model_validate(d["profile"])
            except (ValidationError, KeyError):
                raise FluorosimError(f"session {session_id}: event {e['id']} records an exercise this fluorosim cannot "
                                     "read (written by another version?); update fluorosim to report it") from None
            progress = ExerciseProgress(exercise, t)
            targets = [task.target for task in exercise.tasks]
            scope = Scope(targets=targets, start_t=t)
            task_scopes = [Scope(targets=[task.target]) for task in exercise.tasks]
            live = {"exercise": exercise, "progress": progress, "scope": scope, "tasks": task_scopes,
                    "path": d.get("path", ""), "start_t": t}
            runs.append(live)
            whole.targets = whole.targets + [tg for tg in targets if tg not in whole.targets]
        elif kind == "task_skip" and live is not None:
            live["progress"].skip(t)
        elif kind == "exercise_end":
            close_live(t)
        # A task that just became current starts its own clock.
        if live is not None:
            for ts, task in zip(live["tasks"], live["progress"].tasks):
                if ts.start_t is None and task.started_t is not None:
                    ts.start_t = task.started_t
    close_live(t)
    # The session judges blank exposures only against the exercise running when each began.
    whole_fig = whole.figures()
    if whole.targets:
        judged = [x for x in exposures if len(x.scopes) > 1]
        whole_fig["blank_exposures"] = sum(1 for x in judged if not any(shows(b, tg) for b in x.beams for tg in x.scopes[1].targets))
        whole_fig["judged_exposures"] = len(judged)
        whole_fig["tasks_met"] = sum(r["progress"].met_count() for r in runs)
        whole_fig["time_to_first_on_target_s"] = (runs[0]["scope"].figures()["time_to_first_on_target_s"] if runs else None)
    else:
        whole_fig["judged_exposures"] = 0
    return {
        "session": {"id": session["id"], "trainee": trainee_of(events, session["operator"]), "operator": session["operator"],
                    "case": session["case_title"], "fluoroscope": session["fluoroscope"],
                    "started_wall": session["started_wall"], "ended_wall": session["ended_wall"],
                    "end_reason": session["end_reason"], "ledger_totals": {
                        "fluoro_time_s": session["fluoro_time_s"], "air_kerma_mgy": session["air_kerma_mgy"],
                        "dap_gy_cm2": session["dap_gy_cm2"], "runs": session["runs"], "saves": session["saves"]}},
        "metrics": whole_fig,
        "exercises": [_exercise_out(r, t0) for r in runs],
        "saves": saves_out,
        "exposures": [{"start_s": x.start_t - t0, "end_s": None if x.end_t is None else x.end_t - t0,
                       "images": len(x.beams)} for x in exposures],
        "series": series,
    }


def _exercise_out(run: dict, t0: float) -> dict:
    ex: ExerciseProfile = run["exercise"]
    progress: ExerciseProgress = run["progress"]
    fig = run["scope"].figures()
    fig["tasks_met"] = progress.met_count()
    tasks = []
    for task_run, scope in zip(progress.tasks, run["tasks"]):
        tf = scope.figures()
        tasks.append({"name": task_run.name, "state": task_run.state, "instruction": ex.tasks[task_run.index].instruction,
                      "started_s": None if task_run.started_t is None else task_run.started_t - t0,
                      "ended_s": None if task_run.ended_t is None else task_run.ended_t - t0,
                      "time_to_met_s": (task_run.ended_t - task_run.started_t
                                        if task_run.state == "met" and task_run.ended_t is not None
                                        and task_run.started_t is not None else None),
                      "metrics": tf,
                      "saves": [{"n": n, "t_s": ts - t0, "verdict": None if v is None else v.as_dict()}
                                for ts, n, v in task_run.saves]})
    refs = {}
    for key, value in ex.references.items():
        values = value if isinstance(value, list) else [value]
        refs[key] = [r.model_dump() for r in values]
    return {"title": ex.title, "briefing": ex.briefing, "path": run["path"], "started_s": run["start_t"] - t0,
            "ended_s": None if progress.t_end is None else progress.t_end - t0,
            "metrics": fig, "tasks": tasks, "references": refs}


def trainee_sessions(conn: sqlite3.Connection, name: str, since: float | None = None, until: float | None = None) -> list[int]:
    """Ids of the sessions of trainee `name` (the last name entered in each, else its operator)
    that started in [since, until), oldest first."""
    ids = []
    query = "SELECT id, operator FROM sessions WHERE started_wall >= ? AND started_wall < ? ORDER BY started_wall, id"
    for sid, operator in conn.execute(query, (since if since is not None else -1e300, until if until is not None else 1e300)).fetchall():
        names = [json.loads(r[0]).get("name") for r in conn.execute(
            "SELECT detail FROM events WHERE session_id = ? AND kind = 'trainee' ORDER BY id", (sid,))]
        who = names[-1] if names else operator
        if who.strip().casefold() == name.strip().casefold():
            ids.append(sid)
    return ids
