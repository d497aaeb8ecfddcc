"""The shipped exercises: their targets sit where the built-in child's anatomy puts the organs,
and images of known pose are judged as geometry says; broken exercises name file, line, field."""

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from teaching_script import II, pose

from appliance.cli import main
from appliance.config import load_profile
from appliance.config.exercise import ExerciseProfile
from appliance.patient import anatomy, builtin
from appliance.teaching.views import Beam, judge, target_centre, view_detail

REPO = Path(__file__).resolve().parents[1]
VCUG = load_profile(REPO / "configs/exercises/vcug-child.yaml", ExerciseProfile)
POSITIONING = load_profile(REPO / "configs/exercises/positioning-basics.yaml", ExerciseProfile)


def task(exercise, name):
    return next(t for t in exercise.tasks if t.name == name)


def beam(T, zoom=1, collimation=None, t_case=None):
    return Beam.of(view_detail(II, T, zoom, collimation, t_case))


def test_vcug_targets_are_the_anatomy():
    # Early filling: the 80 mL bladder rises from the neck by its vertical semi-axis.
    r80 = anatomy.bladder_radii(80.0)
    early = task(VCUG, "early filling AP").target.sphere
    assert np.allclose(early.centre_mm, np.array(anatomy.BLADDER_NECK) + [0, 0, r80[2]], atol=1.0)
    assert early.radius_mm >= r80.max() - 3.5
    # The ureters end at (+-14, 8, -150): anatomy.paint_breathing draws them there.
    assert task(VCUG, "left UVJ oblique").target.sphere.centre_mm == (14, 8, -150)
    assert task(VCUG, "right UVJ oblique").target.sphere.centre_mm == (-14, 8, -150)
    # The posterior urethra box holds the prostatic and membranous urethra with its lumen.
    box = task(VCUG, "voiding urethra").target.box
    for p, r in zip(anatomy.URETHRA_PATH[:4], anatomy.URETHRA_RADII[:4]):
        assert all(lo <= c - r and c + r <= hi for c, lo, hi in zip(p, box.min_mm, box.max_mm))
    # Phase windows: the stages of the built-in timeline (4 s each, 32 s loop).
    stage_of = {s.name: i for i, s in reversed(list(enumerate(builtin.STAGES)))}
    step = builtin.PHASES_PER_STAGE * builtin.PHASE_STEP_S
    for name, stage_names in (("early filling AP", ["filling"]), ("left UVJ oblique", ["full"]),
                              ("voiding urethra", ["voiding begins", "voiding"]),
                              ("post-void bladder and kidneys", ["post-void residual"])):
        ph = task(VCUG, name).phase
        assert ph.period_s == builtin.SEQUENCE_S
        stages = {builtin.STAGES[int(t // step)].name for t in np.arange(ph.start_s, ph.end_s, 0.5)}
        assert stages == set(stage_names), name
        assert stage_of[stage_names[0]] * step == ph.start_s
    # The carina and the right dome of the positioning drill.
    assert task(POSITIONING, "carina").target.sphere.centre_mm == (0, 8, 122)
    assert task(POSITIONING, "right dome at expiration").target.sphere.centre_mm == anatomy.RIGHT_DOME


def test_uvj_oblique_is_judged_by_the_geometry():
    uvj = task(VCUG, "left UVJ oblique")
    oblique = (math.sin(math.radians(35)), -math.cos(math.radians(35)), 0.0)
    T = pose(oblique, uvj.target.sphere.centre_mm)
    v = judge(uvj, beam(T, collimation=(150, 150), t_case=13.0))
    assert v.met and v.off_axis_mm == pytest.approx(0.0, abs=0.01) and v.angle_deg < 0.2
    # The timeline loops: two loops later is the same full bladder.
    assert judge(uvj, beam(T, collimation=(150, 150), t_case=13.0 + 64)).met
    v = judge(uvj, beam(T, collimation=(150, 150), t_case=20.0))
    assert not v.met and v.reasons == ("case time 20.0 s, not full bladder (12-16 s)",)
    v = judge(uvj, beam(T, t_case=13.0))
    assert v.reasons == ("not collimated",)
    # An AP image of the same point is 35 degrees from the oblique asked for.
    v = judge(uvj, beam(pose((0, -1, 0), uvj.target.sphere.centre_mm), collimation=(150, 150), t_case=13.0))
    assert v.angle_deg == pytest.approx(35.0, abs=0.1) and len(v.reasons) == 1 and "35 deg" in v.reasons[0]
    # 50 mm off to the side at the target: centred too far off (35 mm allowed), still in the field.
    off = pose(oblique, np.array(uvj.target.sphere.centre_mm) + [0, 0, 50])
    v = judge(uvj, beam(off, collimation=(200, 200), t_case=13.0))
    assert v.in_field and v.off_axis_mm == pytest.approx(50.0, abs=0.01) and "50 mm off" in v.reasons[0]


def test_whole_target_and_zoom_for_the_urethra():
    ure = task(VCUG, "voiding urethra")
    direction = (0.5, -math.sqrt(3) / 2, 0.0)
    T = pose(direction, target_centre(ure.target))
    assert judge(ure, beam(T, zoom=2, t_case=20.0)).met
    assert judge(ure, beam(T, zoom=1, t_case=20.0)).reasons == ("zoom 1 (use 2, 3, 4)",)
    # Blades closed to 20 mm (the minimum): only part of the 38 mm long urethra is in the field.
    v = judge(ure, beam(T, zoom=2, collimation=(20, 20), t_case=20.0))
    assert v.in_field and not v.whole_in_field and v.reasons == ("only part of the posterior urethra in the field",)


def test_a_target_behind_the_focal_spot_is_not_in_the_field():
    early = task(VCUG, "early filling AP")
    # Beam along +z (toward the head), central ray through z = 300: the source sits at
    # z = 300 - 620 = -320, below the bladder (z = -124), which is then in front of it...
    assert beam(pose((0, 0, 1), (0, 0, 300)), t_case=5.0).in_field(np.array([[0.0, -15.0, -124.0]]))[0]
    # ...but through z = 700 the source is at z = 80, the bladder behind the tube: never in the field.
    assert not judge(early, beam(pose((0, 0, 1), (0, 0, 700)), t_case=5.0)).in_field
    # And through z = -700 the detector is at z = -1320 + 1000 = -320: the bladder lies beyond it.
    assert not judge(early, beam(pose((0, 0, 1), (0, 0, -700)), t_case=5.0)).in_field


BROKEN = [
    ("box-corners", "      box: {min_mm: [-8, -32, -184], max_mm: [8, -9, -146]}",
     "      box: {min_mm: [-8, -32, -184], max_mm: [8, -40, -146]}", "tasks[3].target.box.max_mm"),
    ("unknown-metric", "  tasks_met:", "  task_met:", "references.task_met"),
    ("zero-beam", "[0.574, -0.819, 0], within_deg: 20}", "[0, 0, 0], within_deg: 20}", "tasks[1].projection.beam_direction"),
    ("window-past-period", "{start_s: 28, end_s: 32, period_s: 32", "{start_s: 28, end_s: 33, period_s: 32",
     "tasks[4].phase.end_s"),
    ("bad-zoom", "zoom: [2, 3, 4]", "zoom: [2, 3, 5]", "tasks[3].field.zoom[2]"),
    ("typo", "      centred_within_mm: 40", "      centered_within_mm: 40", "tasks[4].field.centered_within_mm"),
]


@pytest.mark.parametrize("old, new, field", [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN])
def test_broken_exercise_names_file_line_and_field(tmp_path, capsys, old, new, field):
    configs = tmp_path / "configs"
    shutil.copytree(REPO / "configs", configs)
    path = configs / "exercises" / "vcug-child.yaml"
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    line = next(i + 1 for i, l in enumerate(path.read_text().splitlines()) if new.strip() in l)
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and err[1] == "1 problem(s) found", err
    assert f"vcug-child.yaml:{line}: {field}:" in err[0], (err, line)
