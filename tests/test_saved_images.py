"""Saved images: PNG and DICOM RF with the geometry and exposure of the moment."""

import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pydicom
import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from appliance.errors import FluorosimError
from appliance.records.ledger import Ledger
from appliance.records.saved_images import save_image
from appliance.records.study import saved_image_context
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)


def console_after_pulsed_run():
    c = Console(II, KEYMAP, t0=0.0)
    for t, key in ((0.0, "KEY_KP5"), (0.1, "KEY_KP2"), (0.2, "KEY_KP9"), (0.3, "KEY_KP9"), (0.4, "KEY_KP6")):
        c.handle(InputEvent(t, "keypad", key, True))
    c.handle(InputEvent(1.0, "pedal", "pedal", True))
    c.handle(InputEvent(7.0, "pedal", "pedal", False))
    c.handle(InputEvent(8.0, "keypad", "KEY_KPPLUS", True))
    return c.snapshot()


def study_of_session(tmp_path, session_id=1, operator="Trainee"):
    """A real ledger session (for the study UIDs and the patient); `session_id` sessions are started."""
    with Ledger(tmp_path / "ledger.sqlite") as ledger:
        for _ in range(session_id):
            if ledger.session_id is not None:
                ledger.end_session(1.7e9)
            sid = ledger.start_session(operator, "Child torso", II.name, t_wall=1.7e9, t_monotonic=0.0,
                                       patient={"sex": "O", "age_years": 6, "weight_kg": 21, "height_m": 1.16})
        study, _ = saved_image_context(*ledger.session_rows(sid), 1)
    return study


def test_png_and_dicom_carry_pixels_geometry_and_exposure(tmp_path):
    state = console_after_pulsed_run()
    assert state.zoom == 2 and state.collimation_mm == (150.0, 160.0) and state.held
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, size=(400, 500), dtype=np.uint8)
    png, dcm = save_image(image, state, II, tmp_path, t_wall=1_700_000_000.0, study=study_of_session(tmp_path, 12),
                          event_uid=None)
    assert png.name == "image-000012-0001.png" and dcm.name == "image-000012-0001.dcm"
    assert np.array_equal(cv2.imread(str(png), cv2.IMREAD_UNCHANGED), image)
    ds = pydicom.dcmread(dcm)
    assert np.array_equal(ds.pixel_array, image)
    assert ds.Modality == "RF" and ds.PixelIntensityRelationship == "DISP"
    assert float(ds.KVP) == 75.0 and ds.XRayTubeCurrent == 2 and ds.RadiationMode == "PULSED"
    assert float(ds.AveragePulseWidth) == 10.0 and ds.ExposureTime == 10
    assert float(ds.DistanceSourceToDetector) == 1000.0 and float(ds.DistanceSourceToPatient) == 620.0
    # Zoom 2 is a 170 mm field over the image's 500 columns.
    pitch = 170.0 / 500
    assert [float(v) for v in ds.ImagerPixelSpacing] == pytest.approx([pitch, pitch])
    assert ds.FieldOfViewShape == "ROUND" and ds.FieldOfViewDimensions == 170
    # Blades 150 mm x 160 mm, centred.
    assert ds.CollimatorLeftVerticalEdge == round((500 - 150 / pitch) / 2)
    assert ds.CollimatorRightVerticalEdge == round((500 + 150 / pitch) / 2)
    assert ds.CollimatorUpperHorizontalEdge == round((400 - 160 / pitch) / 2)
    # Worked by hand: 6 s of pulsed-15 at zoom 2 is the pulses at 1 + k/15 s, k = 0..89, each
    # rate/60/15 mGy with the profile's zoom-2 rate. The blades (150 x 160 mm) are clipped by the
    # 170 mm round field (the rectangle's corners lie outside it), and the field at the detector
    # (SID 1000 mm) is scaled to the reference point at 620 - 150 = 470 mm.
    rate_mgy_per_min = II.zoom_levels[1].air_kerma_rate_mgy_per_min["pulsed-15"]
    kerma_mgy = 90 * rate_mgy_per_min / 60 / 15
    r, n = 85.0, 200_000
    xs = (np.arange(n) + 0.5) * 75.0 / n
    area_mm2 = 4 * float(np.minimum(80.0, np.sqrt(r * r - xs * xs)).sum()) * 75.0 / n
    dap_gy_cm2 = kerma_mgy / 1000 * area_mm2 / 100 * (470.0 / 1000.0) ** 2
    assert state.air_kerma_mgy == pytest.approx(kerma_mgy, rel=1e-9)
    assert float(ds.ImageAndFluoroscopyAreaDoseProduct) == pytest.approx(dap_gy_cm2 * 10, rel=1e-6)   # dGy cm2
    assert ds.PatientAge == "006Y" and ds.PatientSex == "O"
    if shutil.which("dciodvfy"):
        result = subprocess.run(["dciodvfy", str(dcm)], capture_output=True, text=True)
        errors = [l for l in (result.stdout + result.stderr).splitlines() if l.startswith("Error")]
        assert not errors, result.stderr


def test_float_and_16_bit_images(tmp_path):
    state = console_after_pulsed_run()
    ramp = np.linspace(0.0, 1.0, 256)[None, :].repeat(4, axis=0)
    png, dcm = save_image(ramp, state, II, tmp_path, t_wall=1.7e9, study=study_of_session(tmp_path), event_uid=None)
    assert np.array_equal(pydicom.dcmread(dcm).pixel_array[0], np.arange(256, dtype=np.uint8))
    deep = (np.arange(64 * 64, dtype=np.uint16) * 16).reshape(64, 64)
    png, dcm = save_image(deep, state, II, tmp_path / "deep", t_wall=1.7e9, study=study_of_session(tmp_path / "deep"),
                          event_uid=None)
    assert pydicom.dcmread(dcm).BitsStored == 16 and np.array_equal(pydicom.dcmread(dcm).pixel_array, deep)
    assert np.array_equal(cv2.imread(str(png), cv2.IMREAD_UNCHANGED), deep)


def test_never_overwrites(tmp_path):
    state = console_after_pulsed_run()
    study = study_of_session(tmp_path)
    save_image(np.zeros((8, 8), np.uint8), state, II, tmp_path, t_wall=1.7e9, study=study, event_uid=None)
    with pytest.raises(FluorosimError, match="refusing to overwrite"):
        save_image(np.ones((8, 8), np.uint8), state, II, tmp_path, t_wall=1.7e9, study=study, event_uid=None)
    assert cv2.imread(str(tmp_path / "image-000001-0001.png"), cv2.IMREAD_UNCHANGED).max() == 0
