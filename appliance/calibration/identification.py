"""Pair each detected shadow with its ball of the phantom model (the seed paper's steps 3a-3c).

1. Split the blobs into large and small by k-means on their diameters (k = 2).
2. Find the lines of large balls with RANSAC, in pixel positions undistorted with the
   fluoroscope's current (nominal) intrinsics so the intensifier's pincushion does not
   bend them.
3. Every way of laying two model lines of large balls onto two found lines (which line,
   which direction, which ball at each end) gives a homography of the reference plate;
   the one that predicts the most balls of that plate, each on a blob of the right size,
   wins, and it must win clearly: a tie means the layout cannot be told apart and the
   image is refused rather than guessed.
4. The plate's matches give the phantom's pose (PnP with the nominal intrinsics); the pose
   predicts the balls of the other plate, which are matched to the nearest blobs; pose and
   matches are refined twice.

Every match is gated: a prediction takes a blob only within a fraction of the projected
ball spacing, and each blob serves one ball at most. The final fit re-checks every
residual (`fit.py`), so a wrong pairing cannot pass silently.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from ..config.calibration_phantom import CalibrationPhantomProfile
from ..errors import FluorosimError
from .ball_matching import (
    ball_spacing,
    find_lines,
    match_nearest,
    plate_poses,
    project,
    refine_pose,
    split_by_size,
)
from .blobs import Blobs
from .crowding import crowded, crowding_advice
from .field_of_view import FieldOfView

#: Balls of the second plate that propose its parallax shift (see `_complete`): a handful
#: is enough, as one seen ball gives the right shift.
VOTING_BALLS = 8


class IdentificationFailed(FluorosimError):
    """The phantom could not be recognised in one image; the message says why."""


@dataclass(frozen=True)
class Identification:
    """Which ball each accepted blob shows."""

    sphere_index: np.ndarray  # (m,) index into phantom.spheres
    uv: np.ndarray            # (m, 2) blob centres (pixels)
    blob_index: np.ndarray    # (m,) index into the detected blobs
    T_xray_from_phantom: np.ndarray  # pose from the nominal intrinsics, the fit's start
    unmatched_blobs: int


def identify(blobs: Blobs, phantom: CalibrationPhantomProfile, K0: np.ndarray, dist0: np.ndarray,
             source: str = "image", fov: FieldOfView | None = None) -> Identification:
    """Pair blobs with balls, or raise IdentificationFailed with a one-line reason naming `source`.

    With `fov`, a candidate pairing is also charged for every ball its pose puts well inside
    the field where no blob was found: a wrong pairing predicts balls where there are none.
    """
    det = phantom.detection
    if len(blobs) < 8:
        raise IdentificationFailed(f"{source}: only {len(blobs)} ball shadows found (the phantom has "
                                   f"{len(phantom.spheres)}); check that the phantom is in the field and the exposure")
    large_model = phantom.large_mask()
    blob_large, ratio = split_by_size(blobs.diameter_px)
    model_ratio = phantom.diameters()[large_model].mean() / phantom.diameters()[~large_model].mean()
    if not 0.7 * model_ratio < ratio < 1.4 * model_ratio:
        raise IdentificationFailed(f"{source}: the shadows do not split into large and small balls "
                                   f"(size ratio {ratio:.2f}, the phantom's is {model_ratio:.2f})")
    undist = cv2.undistortPoints(blobs.uv.reshape(-1, 1, 2), K0, dist0, None, None, K0).reshape(-1, 2)

    large_idx = np.nonzero(blob_large)[0]
    lines = find_lines(undist[large_idx], det.line_tolerance_px, det.ransac_iterations)
    lines = [large_idx[l] for l in lines]
    centres = phantom.centres()
    labels = np.array([s.line for s in phantom.spheres])
    plane_z = centres[large_model][0, 2]
    in_plane = np.nonzero(np.isclose(centres[:, 2], plane_z))[0]
    model_lines = {}
    for label in dict.fromkeys(labels[large_model]):
        members = np.nonzero(labels == label)[0]
        direction = centres[members[-1], :2] - centres[members[0], :2]
        model_lines[label] = members[np.argsort(centres[members, :2] @ direction)]
    if len(lines) < 2:
        raise IdentificationFailed(f"{source}: found {len(lines)} line(s) of large balls, need at least 2 of the "
                                   f"{len(model_lines)}; " + _what_to_check(blobs, phantom))

    # Step 3: homography hypotheses from two found lines and two model lines.
    size_ok_for = {i: (blob_large == large_model[i]) for i in in_plane}
    scored: dict[tuple, tuple[int, np.ndarray]] = {}    # pairing -> (its best score, homography)
    best: tuple[int, tuple, np.ndarray] | None = None
    candidates = lines[:4]
    for (li, lj) in itertools.permutations(range(len(candidates)), 2):
        img_i, img_j = candidates[li], candidates[lj]
        for (ma, mb) in itertools.permutations(model_lines, 2):
            mod_a, mod_b = model_lines[ma], model_lines[mb]
            if len(img_i) > len(mod_a) or len(img_j) > len(mod_b):
                continue
            for flip_a, flip_b in itertools.product((False, True), repeat=2):
                ends_i = (img_i[0], img_i[-1]) if not flip_a else (img_i[-1], img_i[0])
                ends_j = (img_j[0], img_j[-1]) if not flip_b else (img_j[-1], img_j[0])
                for sa in _end_choices(len(img_i), len(mod_a)):
                    for sb in _end_choices(len(img_j), len(mod_b)):
                        src = np.array([centres[mod_a[sa[0]], :2], centres[mod_a[sa[1]], :2],
                                        centres[mod_b[sb[0]], :2], centres[mod_b[sb[1]], :2]], np.float32)
                        dst = undist[[ends_i[0], ends_i[1], ends_j[0], ends_j[1]]].astype(np.float32)
                        result = _score_homography(src, dst, centres, in_plane, undist, size_ok_for, det.match_gate_fraction)
                        if result is None:
                            continue
                        score, assignment, H = result
                        key = tuple(sorted(assignment.items()))
                        if key not in scored or score > scored[key][0]:
                            scored[key] = (score, H)
                        if best is None or score > best[0]:
                            best = (score, key, H)
    if best is None or best[0] < 6:
        advice = crowding_advice(len(blobs), blobs.crowded, phantom)
        raise IdentificationFailed(f"{source}: the large-ball lines do not match the phantom's layout "
                                   f"({'no' if best is None else best[0]} balls of the reference plate explained)"
                                   + (f"; {advice}" if advice else ""))
    # A plate seen from below is a mirrored homography that can explain nearly as many balls of
    # the plate as the truth; only the other plate tells them apart. So the best few distinct
    # pairings each go through the 3-D step, and the winner must explain clearly more balls.
    distinct: list[tuple[int, tuple, np.ndarray]] = []
    for key, (score, H) in sorted(scored.items(), key=lambda kv: -kv[1][0]):
        if score < best[0] - 4 or len(distinct) >= 6:
            break
        if not any(_same_within(key, k) for _, k, _ in distinct):
            distinct.append((score, key, H))
    outcomes: list[Identification] = []
    last_error: IdentificationFailed | None = None
    for _, key, H in distinct:
        try:
            outcomes.extend(_complete(dict(key), H, blobs, undist, phantom, blob_large, K0, dist0, source))
        except IdentificationFailed as e:
            last_error = e
    if not outcomes:
        raise last_error or IdentificationFailed(f"{source}: no pairing of the reference plate could be completed")
    scores = [_support(o, phantom, K0, dist0, fov) for o in outcomes]
    order = np.argsort([-s for s, _ in scores], kind="stable")
    # Different starts that end in the same pairing are one answer, not a rival.
    kept: list[int] = []
    seen: list[tuple] = []
    for i in order:
        mapping = tuple(zip(outcomes[i].sphere_index.tolist(), outcomes[i].blob_index.tolist()))
        if not any(_same_within(mapping, m) for m in seen):
            seen.append(mapping)
            kept.append(i)
    # Only pairings some camera can produce compete; of those the best must lead clearly.
    viable: list[tuple[Identification, tuple[int, int]]] = []
    refusal: IdentificationFailed | None = None
    for i in kept:
        if viable and scores[i][0] < viable[0][1][0] - 2:
            break
        try:
            checked = _check_camera_explains(outcomes[i], phantom, K0, dist0, source)
        except IdentificationFailed as e:
            refusal = refusal or e
            continue
        viable.append((checked, scores[i]))
    if not viable:
        raise refusal or IdentificationFailed(f"{source}: no camera explains any pairing of the balls")
    if len(viable) > 1:
        raise IdentificationFailed(f"{source}: the phantom's orientation is ambiguous (two different pairings explain "
                                   f"{len(viable[0][0].sphere_index)} and {len(viable[1][0].sphere_index)} balls); "
                                   + _what_to_check(blobs, phantom))
    found, (_, expected) = len(viable[0][0].sphere_index), viable[0][1]
    if expected and found < 0.75 * expected:
        raise IdentificationFailed(f"{source}: only {found} of the {expected} balls the best pose puts in the field "
                                   "were found; check the exposure and that nothing covers the phantom")
    return _without_overlaps(viable[0][0], phantom, K0, dist0)


def _what_to_check(blobs: Blobs, phantom: CalibrationPhantomProfile) -> str:
    """The advice closing a refusal: crowded shadows (a tilt) when many were dropped, else the field."""
    return crowding_advice(len(blobs), blobs.crowded, phantom) or "check that the whole phantom is in the field"


def _without_overlaps(found: Identification, phantom: CalibrationPhantomProfile, K0, dist0) -> Identification:
    """Drop balls whose shadow touches another ball's: one blob then holds two balls and its
    centre belongs to neither. Detection cannot see it (it finds one blob); the pose can."""
    T = found.T_xray_from_phantom
    predicted = project(T, phantom.centres(), K0, dist0)
    depth = phantom.centres() @ T[2, :3] + T[2, 3]
    d = K0[0, 0] * phantom.diameters() / depth
    keep = ~crowded(predicted, d)[found.sphere_index]
    return Identification(found.sphere_index[keep], found.uv[keep], found.blob_index[keep], T,
                          found.unmatched_blobs + int((~keep).sum()))


def _check_camera_explains(found: Identification, phantom: CalibrationPhantomProfile, K0, dist0,
                           source: str) -> Identification:
    """The pairing less any pair no camera agrees with; refuse a pairing no camera can produce.

    The pairing's balls are fitted alone with free focal lengths and k1 (the principal point
    and the rest held): a right pairing leaves residuals at the noise of the blob centres,
    whereas a wrong one, a mirror image for instance, leaves pixels, whatever the camera.
    Single pairs beyond `final_gate_px` (a spurious blob where a ball is hidden, a shadow
    cut by another) are dropped one by one, worst first; the median decides the rest.
    """
    from .fit import View, fit_views

    view = View(source, phantom.centres()[found.sphere_index], found.uv, found.sphere_index, found.T_xray_from_phantom)
    fixed = frozenset({"cx", "cy", "k2", "p1", "p2", "k3"})
    fit = fit_views([view], K0, dist0, final_gate_px=phantom.detection.final_gate_px, min_spheres=6, fixed=fixed)
    if not fit.views:
        raise IdentificationFailed(f"{source}: the identified balls cannot be fitted by any camera")
    residuals = np.hypot(*fit.views[0].residuals_px.T)
    limit = phantom.detection.max_identification_median_px
    if fit.views[0].dropped > len(found.sphere_index) // 4 or np.median(residuals) > limit:
        raise IdentificationFailed(f"{source}: no camera explains the pairing of balls (median residual "
                                   f"{np.median(residuals):.1f} px, limit {limit} px, {fit.views[0].dropped} pairs "
                                   "refused); is the image mirrored, or a different phantom?")
    keep = np.isin(found.sphere_index, fit.views[0].sphere_index)
    return Identification(found.sphere_index[keep], found.uv[keep], found.blob_index[keep], found.T_xray_from_phantom,
                          found.unmatched_blobs + int((~keep).sum()))


def _support(found: Identification, phantom: CalibrationPhantomProfile, K0, dist0, fov: FieldOfView | None) -> tuple[int, int]:
    """(balls found minus balls predicted clearly inside the field but not found, balls predicted there)."""
    if fov is None:
        return len(found.sphere_index), 0
    predicted = project(found.T_xray_from_phantom, phantom.centres(), K0, dist0)
    radius_px = K0[0, 0] * phantom.diameters() / 2 / found.T_xray_from_phantom[2, 3]
    clearly_inside = fov.distance_inside(predicted) > 2 * radius_px + phantom.detection.fov_margin_px + 5
    missing = int(np.sum(clearly_inside & ~np.isin(np.arange(len(predicted)), found.sphere_index)))
    return len(found.sphere_index) - missing, int(clearly_inside.sum())


def _complete(assignment: dict[int, int], H: np.ndarray, blobs: Blobs, undist: np.ndarray,
              phantom: CalibrationPhantomProfile, blob_large: np.ndarray, K0: np.ndarray, dist0: np.ndarray,
              source: str) -> list[Identification]:
    """Step 4 for one pairing of the reference plate: find the other plate, then fit a pose.

    Seen through a narrow beam, a plate alone fixes its tilt poorly, so the other plate is
    not predicted from the plate's pose. Instead: a ball at depth offset dz from the
    reference plane appears where the plate's homography puts its (x, y), scaled about the
    principal point by the depth ratio, plus one shift common to the whole plate (the
    parallax of the tilt). That shift is found by voting over ball-blob pairs; the best few
    shifts each give a full 3-D pose (non-planar PnP with the nominal intrinsics), refined by
    re-matching every ball twice. The caller ranks what comes back.
    """
    det = phantom.detection
    centres = phantom.centres()
    large_model = phantom.large_mask()
    sph = np.array(list(assignment.keys()))
    blb = np.array([assignment[s] for s in sph])
    starts = plate_poses(centres[sph], blobs.uv[blb], K0, dist0)
    if not starts:
        raise IdentificationFailed(f"{source}: no phantom pose fits the reference plate's balls")
    T0 = starts[0]
    plane_z = centres[sph[0], 2]
    other = np.nonzero(~np.isclose(centres[:, 2], plane_z))[0]
    c = K0[:2, 2]
    shifts = [np.zeros(2)]
    if len(other):
        on_plane = centres[other].copy()
        on_plane[:, 2] = plane_z
        z_plane = (on_plane @ T0[:3, :3].T + T0[:3, 3])[:, 2]
        z_ball = (centres[other] @ T0[:3, :3].T + T0[:3, 3])[:, 2]
        xy1 = np.concatenate([on_plane[:, :2], np.ones((len(other), 1))], axis=1) @ H.T
        base = c + (z_plane / z_ball)[:, None] * (xy1[:, :2] / xy1[:, 2:3] - c)
        free = np.setdiff1d(np.arange(len(blobs)), blb)
        gate = det.match_gate_fraction * ball_spacing(base) if len(other) > 1 else 10.0
        votes: list[tuple[int, np.ndarray]] = []
        # Any one ball of the other plate that is seen proposes the true shift, so only the
        # few predicted nearest the plate's middle (surely in the field) propose: each
        # proposal is scored against every ball, which for a grid of hundreds of balls
        # would otherwise cost the fourth power of their number.
        proposers = np.argsort(np.linalg.norm(base - np.median(base, axis=0), axis=1))[:VOTING_BALLS]
        for i in proposers:
            ball = other[i]
            for j in free:
                if blob_large[j] != large_model[ball]:
                    continue
                shift = undist[j] - base[i]
                p, o = match_nearest(base + shift, undist[free], gate)
                ok = blob_large[free[o]] == large_model[other[p]]
                votes.append((int(ok.sum()), shift))
        votes.sort(key=lambda v: -v[0])
        if votes:
            shifts = []
            for count, shift in votes:
                if count < votes[0][0] - 3 or len(shifts) >= 4:
                    break
                if all(np.linalg.norm(shift - s) > gate for s in shifts):
                    shifts.append(shift)
    results = []
    for shift in shifts:
        p_all, o_all = sph, blb
        if len(other):
            p, o = match_nearest(base + shift, undist[free], gate)
            ok = blob_large[free[o]] == large_model[other[p]]
            p_all = np.concatenate([sph, other[p[ok]]])
            o_all = np.concatenate([blb, free[o[ok]]])
        T = refine_pose(centres[p_all], blobs.uv[o_all], K0, dist0, guess=T0)
        if T is None or T[2, 3] <= 0:
            continue
        p, o = p_all, o_all
        for _ in range(2):
            predicted = project(T, centres, K0, dist0)
            p, o = match_nearest(predicted, blobs.uv, det.match_gate_fraction * ball_spacing(predicted))
            ok = blob_large[o] == large_model[p]
            p, o = p[ok], o[ok]
            if len(p) < 6:
                break
            T_new = refine_pose(centres[p], blobs.uv[o], K0, dist0, guess=T)
            if T_new is None:
                break
            T = T_new
        if len(p) >= 6:
            order = np.argsort(p)
            results.append(Identification(sphere_index=p[order], uv=blobs.uv[o[order]], blob_index=o[order],
                                          T_xray_from_phantom=T, unmatched_blobs=int(len(blobs) - len(p))))
    if not results:
        raise IdentificationFailed(f"{source}: too few balls match the layout predicted from the reference plate")
    return results


def _end_choices(n_found: int, n_model: int):
    """(model index of the first found ball, of the last) for n_found balls seen of a line of n_model."""
    for first in range(0, n_model - n_found + 1):
        for last in range(first + n_found - 1, n_model):
            yield first, last


def _same_within(a: tuple, b: tuple) -> bool:
    """Two assignments that agree on most balls are one pairing, seen through slightly different homographies."""
    da, db = dict(a), dict(b)
    agree = sum(1 for k in set(da) & set(db) if da[k] == db[k])
    return agree >= 0.5 * min(len(da), len(db))


def _score_homography(src, dst, centres, in_plane, undist, size_ok_for, gate_fraction):
    H = cv2.getPerspectiveTransform(src, dst)
    if H is None or not np.all(np.isfinite(H)):
        return None
    assignment: dict[int, int] = {}
    for _ in range(2):
        pts = np.concatenate([centres[in_plane, :2], np.ones((len(in_plane), 1))], axis=1) @ H.T
        if np.any(pts[:, 2] <= 0):
            return None
        predicted = pts[:, :2] / pts[:, 2:3]
        gate = gate_fraction * ball_spacing(predicted)
        p, o = match_nearest(predicted, undist, gate)
        good = np.array([size_ok_for[in_plane[pi]][oi] for pi, oi in zip(p, o)], bool)
        p, o = p[good], o[good]
        assignment = {int(in_plane[pi]): int(oi) for pi, oi in zip(p, o)}
        if len(p) < 4:
            return None
        H2, _ = cv2.findHomography(centres[in_plane[p], :2], undist[o], 0)
        if H2 is None:
            break
        H = H2
    return len(assignment), assignment, H
