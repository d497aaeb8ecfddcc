"""A recorded training session with saved images and its dose report, made by the real
console, ledger and writers, for the DICOM tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from teaching_script import pose

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.config.dicom import Dicom
from appliance.console.state import Console
from appliance.records import dicom, rdsr
from appliance.records.identity import device_uid, equipment_of
from appliance.records.ledger import Ledger
from appliance.records.saved_images import save_image
from appliance.records.study import saved_image_context
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
T0 = 1_700_000_000.0   # 2023-11-14T22:13:20Z
IDENTITY = Dicom(institution="St Elsewhere Teaching Hospital", department="Radiology training",
                 station_name="FLUOROSIM-3", serial_number="FS-0042", patient_id_issuer="STELSEWHERE-SIM")
PATIENT = {"sex": "O", "age_years": 6, "weight_kg": 21.0, "height_m": 1.16}
# The C-arm at LAO 30 CRA 20 (beam direction in the patient's LPS frame), central ray through the origin.
POSE = pose((0.5 * np.cos(np.radians(20)), -np.sqrt(3) / 2 * np.cos(np.radians(20)), np.sin(np.radians(20))), (0, 0, 0))


@dataclass
class RecordedSession:
    ledger: Path
    session_id: int
    images: list[Path]
    report: Path
    report_bytes: bytes
    run_on_hashes: list[str]       # the fluoro_on event of each run, in order
    saved_after_run: list[int]     # for each saved image, the index of the run it shows


def press(console, t, key, pressed=True):
    return console.handle(InputEvent(t, "keypad", key, pressed))


def record_session(tmp: Path, operator: str = "Jane Q Trainee", rng_seed: int = 0) -> RecordedSession:
    """Two fluoroscopy runs; an image saved during the first (live), one after it (held) and one
    after the second; the session ended; its RDSR written beside the images."""
    tmp.mkdir(parents=True, exist_ok=True)
    ledger_path = tmp / "ledger.sqlite"
    uid = device_uid(tmp / "device-identity")
    rng = np.random.default_rng(rng_seed)
    images: list[Path] = []
    with Ledger(ledger_path) as ledger:
        console = Console(II, KEYMAP, t0=0.0)
        sid = ledger.start_session(operator, "Child torso", II.name, t_wall=T0, t_monotonic=0.0,
                                   equipment=equipment_of(II, IDENTITY, uid), patient=PATIENT)
        timeline = [   # run lazily: each step's console snapshot is the state at its save
            lambda: press(console, 1.0, "pedal") + console.tick(2.0),
            lambda: press(console, 2.5, "KEY_KPPLUS"),                          # live save in run 1
            lambda: press(console, 4.0, "pedal", False) + press(console, 5.0, "KEY_KPPLUS"),   # held save of run 1
            lambda: press(console, 10.0, "pedal") + console.tick(12.0) + press(console, 13.0, "pedal", False),
            lambda: press(console, 14.0, "KEY_KPPLUS"),                         # held save of run 2
        ]
        for make in timeline:
            step = make()
            ledger.record(step)
            if any(e.kind == "save" for e in step):
                state = console.snapshot()
                session, events = ledger.session_rows(sid)
                study, event_uid = saved_image_context(session, events, state.save_count)
                pixels = rng.integers(0, 256, size=(64, 80), dtype=np.uint8)
                _, dcm = save_image(pixels, state, II, tmp / "images", t_wall=T0 + events[-1]["t_monotonic"],
                                    study=study, event_uid=event_uid, T_xray_from_ct=POSE)
                images.append(dcm)
        ledger.end_session(T0 + 20.0)
        session, events = ledger.session_rows(sid)
    report_bytes = dicom.encode(rdsr.session_report(session, events))
    report = tmp / "images" / f"session-{sid:06d}.dcm"
    report.write_bytes(report_bytes)
    on_hashes = [e["hash"] for e in events if e["kind"] == "fluoro_on"]
    return RecordedSession(ledger_path, sid, images, report, report_bytes, on_hashes, [0, 0, 1])
