"""Instructor reports: one session, or one trainee across sessions, as HTML with plots and
the same figures as CSV and JSON.

Session report (folder `session-NNNNNN/`): `index.html` with K_a,r and its rate over the
session's console time with every exposure shaded and every save marked, the metrics of
the session and of each exercise against the references the exercise cites, one row per
task, and thumbnails of the saved images with their verdicts; `report.json` (everything,
as `metrics.session_metrics` gives it), `metrics.csv` (scope, metric, value, unit),
`tasks.csv`, `saves.csv`, `exposures.csv` and `series.csv` (the plotted curve).

Trainee report (folder `trainee-NAME/`): one row per session with the headline metrics,
plots of their trend over the sessions, `sessions.csv` and `report.json`.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import re
import sqlite3
from pathlib import Path

from ..atomic_file import write_atomic
from ..config.exercise import REFERENCE_METRICS
from ..errors import FluorosimError
from ..records.export import iso
from .metrics import session_metrics, trainee_sessions

#: Width of the bins the dose-rate curve averages over (s of console time).
RATE_BIN_S = 1.0
#: Longest side of a saved image's thumbnail in the report (pixels).
THUMB_PX = 200

#: Metrics shown in the tables, in order, with a label and a unit.
SHOWN = (
    ("exposures", "exposures (pedal presses)", ""), ("blank_exposures", "blank exposures", ""),
    ("judged_exposures", "exposures during an exercise", ""),
    ("fluoro_time_s", "fluoroscopy time", "s"), ("air_kerma_mgy", "K_a,r", "mGy"), ("dap_gy_cm2", "DAP", "Gy cm2"),
    ("images_saved", "images saved", ""), ("images_on_target", "images on target", ""),
    ("images_off_target", "images off target", ""), ("held_image_saves", "saved from last-image-hold", ""),
    ("collimated_share", "exposure time collimated", "fraction"), ("mean_field_area_cm2", "mean field area", "cm2"),
    ("pulsed_share", "exposure time pulsed", "fraction"),
    ("time_to_first_on_target_s", "time to first on-target image", "s"), ("tasks_met", "tasks met", ""),
)


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"
    return str(value)


def _csv(header: list[str], rows: list[list]) -> bytes:
    buffer = io.StringIO(newline="")
    w = csv.writer(buffer, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buffer.getvalue().encode("utf-8")


def _write(folder: Path, name: str, data: bytes | str) -> Path:
    return write_atomic(folder / name, data.encode("utf-8") if isinstance(data, str) else data)


def _mkdir(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FluorosimError(f"{folder}: cannot create the report folder ({e.strerror or e}); give --out DIR") from None


def dose_rate(series: dict, bin_s: float = RATE_BIN_S) -> tuple[list[float], list[float]]:
    """(bin start s, mean K_a,r rate mGy/min) from the cumulative curve, in bins of `bin_s`:
    each increment is spread evenly over the interval since the point before it, as
    continuous fluoroscopy accrues it."""
    t, k = series["t"], series["air_kerma_mgy"]
    if not t:
        return [], []
    n = int(math.floor(max(t) / bin_s)) + 1
    rate = [0.0] * n
    for i in range(1, len(t)):
        dk, a, b = k[i] - k[i - 1], t[i - 1], t[i]
        if not dk:
            continue
        if b <= a:
            rate[min(int(b // bin_s), n - 1)] += dk
            continue
        j = int(a // bin_s)
        while j * bin_s < b and j < n:
            lo, hi = max(a, j * bin_s), min(b, (j + 1) * bin_s)
            rate[j] += dk * max(hi - lo, 0.0) / (b - a)
            j += 1
    return [i * bin_s for i in range(n)], [r / bin_s * 60.0 for r in rate]


def _plot_session(m: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 5), dpi=100)
    ax_k, ax_r = fig.subplots(2, 1, sharex=True)
    s = m["series"]
    ax_k.plot(s["t"], s["air_kerma_mgy"], color="tab:blue")
    ax_k.set_ylabel("cumulative K_a,r (mGy)")
    t_bins, rate = dose_rate(s)
    ax_r.step(t_bins, rate, where="post", color="tab:red")
    ax_r.set_ylabel("K_a,r rate (mGy/min)")
    ax_r.set_xlabel("session time (s, console clock)")
    end = s["t"][-1] if s["t"] else 0.0
    for x in m["exposures"]:
        for ax in (ax_k, ax_r):
            ax.axvspan(x["start_s"], x["end_s"] if x["end_s"] is not None else end, color="gold", alpha=0.3, lw=0)
    for sv in m["saves"]:
        v = sv["verdict"]
        color = "green" if v and v["met"] else ("grey" if v is None else "darkorange")
        for ax in (ax_k, ax_r):
            ax.axvline(sv["t_s"], color=color, lw=1, ls="--")
        ax_k.annotate(f"#{sv['n']}", (sv["t_s"], 0), xytext=(2, 2), textcoords="offset points", fontsize=7, color=color)
    ax_k.set_title("exposures shaded; saves dashed (green: task met, orange: not met, grey: no task)", fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    _write(path.parent, path.name, buffer.getvalue())


def _thumbnail(src: Path, dst: Path) -> bool:
    import cv2

    image = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE) if src.is_file() else None
    if image is None:
        return False
    scale = THUMB_PX / max(image.shape)
    small = cv2.resize(image, (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale))),
                       interpolation=cv2.INTER_AREA)
    ok, png = cv2.imencode(".png", small)
    if ok:
        _write(dst.parent, dst.name, png.tobytes())
    return bool(ok)


def _reference_rows(metrics: dict, references: dict) -> list[list]:
    rows = []
    for key, refs in references.items():
        value = metrics.get(key)
        for r in refs:
            z = None
            if value is not None and r.get("sd"):
                z = (value - r["value"]) / r["sd"]
            rows.append([key, value, r["value"], r.get("sd"), z, r.get("note", ""), r["source"]])
    return rows


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


STYLE = ("body{font-family:sans-serif;margin:1.5em;max-width:1100px}table{border-collapse:collapse;margin:.5em 0 1.5em}"
         "td,th{border:1px solid #bbb;padding:3px 8px;text-align:left;font-size:90%}th{background:#eee}"
         ".met{color:#060}.not{color:#a50}.thumbs{display:flex;flex-wrap:wrap;gap:12px}"
         ".thumbs figure{margin:0;width:210px;font-size:85%}")


def _metric_rows(scope: str, fig: dict) -> list[list]:
    rows = []
    for key, _label, unit in SHOWN:
        if key in fig:
            rows.append([scope, key, fig[key], unit or REFERENCE_METRICS.get(key, "")])
    for z, s in fig.get("zoom_time_s", {}).items():
        rows.append([scope, f"zoom_{z}_time_s", s, "s"])
    return rows


def write_session_report(conn: sqlite3.Connection, session_id: int, out_dir: Path, images_dir: Path | None = None) -> Path:
    """Write the session report into `out_dir/session-NNNNNN/`; returns its index.html."""
    m = session_metrics(conn, session_id)
    folder = Path(out_dir) / f"session-{session_id:06d}"
    _mkdir(folder)
    _write(folder, "report.json", json.dumps(m, indent=1, allow_nan=False))
    metric_rows = _metric_rows("session", m["metrics"])
    task_rows, ref_rows = [], []
    for i, ex in enumerate(m["exercises"], 1):
        metric_rows += _metric_rows(f"exercise {i}", ex["metrics"])
        ref_rows += [[f"exercise {i}"] + r for r in _reference_rows(ex["metrics"], ex["references"])]
        for j, task in enumerate(ex["tasks"], 1):
            tf = task["metrics"]
            task_rows.append([i, j, task["name"], task["state"], task["started_s"], task["ended_s"], task["time_to_met_s"],
                              tf["exposures"], tf["blank_exposures"], tf["fluoro_time_s"], tf["air_kerma_mgy"],
                              tf["dap_gy_cm2"], tf["images_saved"], tf["images_on_target"], tf["time_to_first_on_target_s"]])
    task_header = ["exercise", "task", "name", "state", "started_s", "ended_s", "time_to_met_s", "exposures",
                   "blank_exposures", "fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2", "images_saved", "images_on_target",
                   "time_to_first_on_target_s"]
    save_rows = [[s["n"], s["t_s"], s["image"], s["task"], None if s["verdict"] is None else s["verdict"]["met"],
                  "" if s["verdict"] is None else "; ".join(s["verdict"]["reasons"]), s["tracked"]] for s in m["saves"]]
    save_header = ["n", "t_s", "image", "task", "met", "reasons", "tracked"]
    ref_header = ["scope", "metric", "value", "reference", "sd", "z", "whose", "source"]
    _write(folder, "metrics.csv", _csv(["scope", "metric", "value", "unit"], metric_rows))
    _write(folder, "tasks.csv", _csv(task_header, task_rows))
    _write(folder, "saves.csv", _csv(save_header, save_rows))
    _write(folder, "references.csv", _csv(ref_header, ref_rows))
    _write(folder, "exposures.csv", _csv(["start_s", "end_s", "images"], [[x["start_s"], x["end_s"], x["images"]]
                                                                         for x in m["exposures"]]))
    s = m["series"]
    _write(folder, "series.csv", _csv(["t_s", "air_kerma_mgy", "dap_gy_cm2", "fluoro_time_s"],
                                      [list(r) for r in zip(s["t"], s["air_kerma_mgy"], s["dap_gy_cm2"], s["fluoro_time_s"])]))
    _plot_session(m, folder / "dose.png")

    thumbs = []
    for sv in m["saves"]:
        name = f"image-{session_id:06d}-{sv['n']:04d}.png"
        shown = images_dir is not None and _thumbnail(Path(images_dir) / name, folder / f"thumb-{sv['n']:04d}.png")
        v = sv["verdict"]
        verdict = ("no exercise task" if sv["task"] is None else
                   f"{sv['task']}: " + ("met" if v and v["met"] else "not met - " + "; ".join(v["reasons"]) if v else
                                        "not met - no tracked image"))
        cls = "met" if v and v["met"] else "not"
        img = f'<img src="thumb-{sv["n"]:04d}.png" alt="saved image {sv["n"]}">' if shown else "<p>(image file not found)</p>"
        thumbs.append(f'<figure>{img}<figcaption>#{sv["n"]} at {sv["t_s"]:.1f} s ({html.escape(sv["image"])})<br>'
                      f'<span class="{cls}">{html.escape(verdict)}</span></figcaption></figure>')
    info = m["session"]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>Session {session_id}</title>"
             f"<style>{STYLE}</style></head><body>",
             f"<h1>Session {session_id}: {html.escape(info['trainee'])}</h1>",
             f"<p>Case {html.escape(info['case'])}; fluoroscope {html.escape(info['fluoroscope'])}; "
             f"started {iso(info['started_wall'])}, ended {iso(info['ended_wall']) or 'not yet'} "
             f"({html.escape(info['end_reason'] or 'open')}).</p>",
             "<h2>Dose over the session</h2><img src='dose.png' alt='dose plot'>",
             "<h2>Metrics</h2>", _table(["scope", "metric", "value", "unit"], metric_rows)]
    if ref_rows:
        parts += ["<h2>Against the references</h2><p>z: (value - reference) / sd.</p>", _table(ref_header, ref_rows)]
    for i, ex in enumerate(m["exercises"], 1):
        items = "".join(f"<li><b>{html.escape(t['name'])}</b>: {html.escape(t['instruction'])} "
                        f"<i>({html.escape(t['state'])})</i></li>" for t in ex["tasks"])
        parts.append(f"<h2>Exercise {i}: {html.escape(ex['title'])}</h2><p>{html.escape(ex['briefing'])}</p><ol>{items}</ol>")
    if task_rows:
        parts += ["<h2>Tasks</h2>", _table(task_header, task_rows)]
    parts += ["<h2>Saved images</h2>", f"<div class='thumbs'>{''.join(thumbs) or '<p>none</p>'}</div>",
              "<p>Figures as data: <a href='report.json'>report.json</a>, <a href='metrics.csv'>metrics.csv</a>, "
              "<a href='tasks.csv'>tasks.csv</a>, <a href='saves.csv'>saves.csv</a>, <a href='references.csv'>references.csv</a>, "
              "<a href='exposures.csv'>exposures.csv</a>, <a href='series.csv'>series.csv</a>.</p></body></html>"]
    return _write(folder, "index.html", "\n".join(parts))


#: Columns of the trainee report, one row per session.
TREND = ("fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2", "exposures", "blank_exposures", "images_saved",
         "images_on_target", "collimated_share", "pulsed_share", "time_to_first_on_target_s", "tasks_met")


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-").lower() or "trainee"


def write_trainee_report(conn: sqlite3.Connection, name: str, out_dir: Path, since: float | None = None,
                         until: float | None = None) -> Path:
    """Write the trainee's report into `out_dir/trainee-NAME/`; returns its index.html."""
    ids = trainee_sessions(conn, name, since, until)
    if not ids:
        raise FluorosimError(f"no sessions of trainee '{name}' in the ledger for that period; "
                             "`fluorosim logs list` shows the sessions")
    sessions = [session_metrics(conn, sid) for sid in ids]
    folder = Path(out_dir) / f"trainee-{_slug(name)}"
    _mkdir(folder)
    rows = []
    for m in sessions:
        titles = "; ".join(ex["title"] for ex in m["exercises"])
        rows.append([m["session"]["id"], iso(m["session"]["started_wall"]), titles] + [m["metrics"].get(k) for k in TREND])
    header = ["session", "started_utc", "exercises"] + list(TREND)
    _write(folder, "sessions.csv", _csv(header, rows))
    _write(folder, "report.json", json.dumps({"trainee": name, "sessions": [
        {"session": m["session"], "metrics": m["metrics"],
         "exercises": [{"title": ex["title"], "metrics": ex["metrics"],
                        "tasks": [{"name": t["name"], "state": t["state"]} for t in ex["tasks"]]} for ex in m["exercises"]]}
        for m in sessions]}, indent=1, allow_nan=False))
    _plot_trends(rows, folder / "trends.png")
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>Trainee {html.escape(name)}</title>"
             f"<style>{STYLE}</style></head><body>", f"<h1>Trainee {html.escape(name)}: {len(ids)} session(s)</h1>",
             "<img src='trends.png' alt='trends'>", _table(header, rows),
             "<p>Figures as data: <a href='sessions.csv'>sessions.csv</a>, <a href='report.json'>report.json</a>. "
             "Each session's own report: <code>fluorosim report session N</code>.</p></body></html>"]
    return _write(folder, "index.html", "\n".join(parts))


def _plot_trends(rows: list[list], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    shown = (("fluoro_time_s", "fluoroscopy time (s)"), ("dap_gy_cm2", "DAP (Gy cm2)"),
             ("blank_exposures", "blank exposures"), ("tasks_met", "tasks met"))
    fig = Figure(figsize=(9, 5), dpi=100)
    axes = fig.subplots(2, 2).ravel()
    x = list(range(1, len(rows) + 1))
    for ax, (key, label) in zip(axes, shown):
        col = 3 + TREND.index(key)
        y = [r[col] if r[col] is not None else float("nan") for r in rows]
        ax.plot(x, y, marker="o")
        ax.set_title(label, fontsize=9)
        ax.set_xticks(x, [str(r[0]) for r in rows], fontsize=7)
        ax.set_xlabel("session", fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    _write(path.parent, path.name, buffer.getvalue())
