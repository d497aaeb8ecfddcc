"""Rigid transforms and the pinhole model, as properties over many random cases (hypothesis).

Truth is mathematics, not the module: a rotation keeps lengths and handedness, a transform and
its inverse compose to the identity, and the pinhole puts X/Z, Y/Z at fx, fy pixels from the
principal point, each along its own axis. OpenCV's projectPoints is the independent check of
the projection with distortion switched off."""

from __future__ import annotations

import math

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.geometry import (
    apply,
    camera_matrix,
    invert,
    make_transform,
    project,
    rigid_problem,
    rotation_about,
    rotation_angle_deg,
)

finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False, allow_infinity=False)
axes = st.tuples(finite, finite, finite).filter(lambda a: math.hypot(*a) > 1e-3)
angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
points = st.lists(st.tuples(finite, finite, finite), min_size=1, max_size=8)


@st.composite
def rigid(draw):
    return make_transform(rotation_about(draw(axes), draw(angles)), draw(st.tuples(finite, finite, finite)))


@settings(max_examples=80, deadline=None)
@given(axis=axes, angle=angles)
def test_rotation_about_is_a_proper_rotation_by_the_angle(axis, angle):
    R = rotation_about(axis, angle)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1.0) < 1e-12
    a = np.asarray(axis) / np.linalg.norm(axis)
    assert np.allclose(R @ a, a, atol=1e-9), "the axis stays put"
    assert abs(rotation_angle_deg(R, np.eye(3)) - abs(math.degrees(angle))) < 1e-5
    # Right-handed: a vector perpendicular to the axis turns toward axis x vector.
    v = np.cross(a, [1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 1.0, 0.0])
    v /= np.linalg.norm(v)
    w = np.cross(a, v)
    assert np.allclose(R @ v, math.cos(angle) * v + math.sin(angle) * w, atol=1e-9)


@settings(max_examples=80, deadline=None)
@given(T=rigid(), pts=points)
def test_inverse_undoes_the_transform_and_keeps_distances(T, pts):
    p = np.asarray(pts)
    assert rigid_problem(T) is None
    assert np.allclose(invert(T) @ T, np.eye(4), atol=1e-9)
    assert np.allclose(apply(invert(T), apply(T, p)), p, atol=1e-7)
    q = apply(T, p)
    assert np.allclose(np.linalg.norm(q[:, None] - q[None], axis=-1), np.linalg.norm(p[:, None] - p[None], axis=-1),
                       atol=1e-7)


@settings(max_examples=50, deadline=None)
@given(T=rigid(), pts=points)
def test_apply_is_the_homogeneous_product(T, pts):
    p = np.asarray(pts)
    by_hand = np.array([(T @ np.array([x, y, z, 1.0]))[:3] for x, y, z in p])
    assert np.allclose(apply(T, p), by_hand, rtol=1e-12, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(a=rigid(), axis=axes, angle=angles)
def test_angle_between_poses_of_4x4_transforms_and_at_the_ends_of_its_range(a, axis, angle):
    """The angle taking pose b to pose a, for 4x4 poses as the tracker passes them; the same pose
    is 0 deg and a half turn is 180 deg, never NaN from rounding past the arccos domain."""
    b = make_transform(rotation_about(axis, angle), a[:3, 3] + 5.0) @ a
    assert abs(rotation_angle_deg(b, a) - abs(math.degrees(angle))) < 1e-5
    same = rotation_angle_deg(a, a)
    assert math.isfinite(same) and same < 1e-5
    half = rotation_angle_deg(make_transform(rotation_about(axis, math.pi), [0.0, 0.0, 0.0]) @ a, a)
    assert math.isfinite(half) and abs(half - 180.0) < 1e-5


def test_the_angle_is_finite_where_rounding_takes_the_cosine_past_its_domain():
    """Rotations whose R R^T has a trace that rounds above 3, and whose half turn's rounds below
    -1 (the first draws of a seeded generator do both; counted below, so the check cannot pass
    without meeting them): the same pose is 0 deg and the half turn 180 deg, never NaN."""
    rng = np.random.default_rng(1)
    past_one = past_minus_one = 0
    for _ in range(20):
        axis = rng.normal(size=3)
        R = rotation_about(axis / np.linalg.norm(axis), rng.uniform(-math.pi, math.pi))
        H = rotation_about(axis / np.linalg.norm(axis), math.pi) @ R
        past_one += (np.trace(R @ R.T) - 1.0) / 2.0 > 1.0
        past_minus_one += (np.trace(H @ R.T) - 1.0) / 2.0 < -1.0
        assert rotation_angle_deg(R, R) < 1e-5
        assert abs(rotation_angle_deg(H, R) - 180.0) < 1e-5
    assert past_one and past_minus_one


@settings(max_examples=50, deadline=None)
@given(T=rigid(), scale=st.floats(min_value=1.001, max_value=10.0), axis=st.integers(0, 2))
def test_scaled_sheared_or_mirrored_matrices_are_not_rigid(T, scale, axis):
    scaled = T.copy()
    scaled[:3, axis] *= scale
    assert rigid_problem(scaled) is not None
    mirrored = T.copy()
    mirrored[:3, axis] *= -1.0
    assert "determinant" in rigid_problem(mirrored)
    sheared = T.copy()
    sheared[:3, axis] += 0.01 * sheared[:3, (axis + 1) % 3]
    assert rigid_problem(sheared) is not None
    nan = T.copy()
    nan[0, 3] = float("nan")
    assert rigid_problem(nan) is not None


@settings(max_examples=80, deadline=None)
@given(fx=st.floats(100, 10000), fy=st.floats(100, 10000), cx=st.floats(-50, 1100), cy=st.floats(-50, 1100),
       x=st.floats(-300, 300), y=st.floats(-300, 300), z=st.floats(50, 3000))
def test_pinhole_puts_each_axis_at_its_own_focal_length(fx, fy, cx, cy, x, y, z):
    K = camera_matrix(fx, fy, cx, cy)
    u, v = project(K, np.array([x, y, z]))
    assert abs(u - (cx + fx * x / z)) <= 1e-9 * max(1.0, abs(u))
    assert abs(v - (cy + fy * y / z)) <= 1e-9 * max(1.0, abs(v))
    cv_uv, _ = cv2.projectPoints(np.array([[x, y, z]], np.float64), np.zeros(3), np.zeros(3), K, np.zeros(5))
    assert np.allclose(cv_uv.reshape(2), [u, v], rtol=1e-9, atol=1e-6)
    # Back along the ray: the pixel's normalised direction times z returns the point.
    back = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z])
    assert np.allclose(back, [x, y, z], rtol=1e-9, atol=1e-6)


def test_a_pose_file_with_an_integer_too_big_for_int64_is_a_problem_not_a_crash():
    # YAML reads 1000000000000000000000000000000 as a Python int; numpy would hold it as an object.
    huge = [[10**30, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    assert "not orthonormal" in rigid_problem(huge)
    assert rigid_problem([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 10**20], [0, 0, 0, 1]]) is None


def test_each_refusal_says_what_is_wrong_and_a_deviation_at_the_tolerance_passes():
    eye = np.eye(4)
    nan = eye.copy()
    nan[0, 3] = np.nan
    assert rigid_problem(nan) == "must contain only finite numbers"
    assert rigid_problem(np.eye(3)) == "must be a 4x4 matrix, got shape (3, 3)"
    row = eye.copy()
    row[3, 3] = 1.5                         # 0.5 off: refused at a tolerance below, accepted at 0.5 itself
    assert rigid_problem(row, tol=0.25) == "last row must be 0 0 0 1"
    assert rigid_problem(row, tol=0.5) is None
    stretched = np.diag([1.25, 1.0, 1.0, 1.0])      # R^T R - I = 0.5625 exactly; det - 1 = 0.25
    assert rigid_problem(stretched, tol=0.5) == "rotation part is not orthonormal (tolerance 0.5)"
    assert rigid_problem(stretched, tol=0.5625) is None
    grown = np.diag([1.25, 1.25, 1.25, 1.0])        # R^T R - I = 0.5625; det - 1 = 0.953125 (to LAPACK's rounding)
    assert rigid_problem(grown, tol=0.9) == "rotation part must have determinant +1 (a mirror is not a rigid motion)"
    assert rigid_problem(grown, tol=abs(np.linalg.det(grown[:3, :3]) - 1.0)) is None


def test_a_transform_takes_opencvs_column_vector_translation():
    import cv2

    R = rotation_about([0, 0, 1], 0.3)
    rvec, _ = cv2.Rodrigues(R)
    tvec = np.array([[12.0], [-4.0], [550.0]])         # solvePnP's shape: 3 x 1
    T = make_transform(cv2.Rodrigues(rvec)[0], tvec)
    np.testing.assert_allclose(T, [[*R[0], 12.0], [*R[1], -4.0], [*R[2], 550.0], [0, 0, 0, 1]], atol=1e-12)
