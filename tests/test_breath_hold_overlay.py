"""BREATH HOLD is on the monitor only where the patient breathes: a static CT has no breath to hold."""

from pathlib import Path

import pytest

from appliance.config import CaseProfile, load_appliance, load_profile
from appliance.console.state import Console
from appliance.daemon.render_worker import overlay_for
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def demo_config():
    return load_appliance(REPO / "configs" / "appliance-demo.yaml")


@pytest.mark.parametrize("case, shown", [("bar-pattern.yaml", False), ("child-torso-vcug.yaml", True),
                                         ("child-torso-breathing.yaml", True)])
def test_breath_hold_is_shown_only_on_a_breathing_case(demo_config, case, shown):
    cfg = demo_config
    cfg = cfg.__class__(**{**cfg.__dict__, "case": load_profile(REPO / "configs" / "cases" / case, CaseProfile)})
    console = Console(cfg.fluoroscope, cfg.keymap, t0=0.0)
    console.handle(InputEvent(1.0, "scripted", "KEY_KPSLASH", True))
    state = console.snapshot()
    assert state.breath_hold                      # the console holds either way (and records it)
    overlay = overlay_for(cfg, state, live=True, saved_flash=False, warnings=[], fps=None)
    assert overlay.breath_hold is shown
