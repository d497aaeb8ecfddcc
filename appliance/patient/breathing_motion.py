"""The moving anatomy of a breathing patient, built from one CT (end-expiration) and its labels.

The CT is split once into three parts:

- the still skeleton: the spine (labels, or bone within `spine_half_width_mm` of the
  midline behind the body's centre) and every bone piece that is not a rib;
- the ribs: each piece of the rib labels, or without them each bone piece within
  `rib_head_max_mm` of the spine, at least `rib_min_length_mm` long, its joint no lower
  than `rib_below_dome_mm` under the diaphragm; a rigid body turned about its
  costovertebral joint (the piece's point nearest the spine) by lambda about the
  left-right axis (pump handle: the front rises) and gamma about the anteroposterior axis
  (bucket handle: the side rises). From HU alone a scapula touching the upper ribs would
  move with them as one piece, so bone that stands taller than `rib_max_height_mm` in
  unbroken vertical lines is taken out first: a rib is a thin tube running round the
  chest, no taller than its own height over the cosine of its slope, while a scapula (and
  the sternum) is a plate standing tens of millimetres tall. A plate that leans or curves
  still stands tall once the bone is widened by `rib_plate_widen_mm` in each axial slice
  for the measurement. With `rib_pleura_max_mm` the pieces are also cut to the bone that
  lines the lungs behind the body's centre. The sternum stays still: give rib labels where
  that matters;
- soft tissue (bone replaced by `bone_fill_hu`), displaced downward by the tendon's
  descent D times a smooth weight: 1 from the lowest point of the diaphragm to the top of
  its dome, falling linearly to 0 at the lung apices (the lungs stretch) and over
  `abdomen_falloff_mm` below (the abdominal organs follow less with depth), and laterally
  the lungs' footprint softened by a Gaussian (the body wall and arms stay).

Why a displacement field rather than the seed's ChainMail: it is evaluated as one shift
per voxel column (tens of milliseconds for a whole CT) and is smooth by construction;
what a radiographer sees of the abdomen, the dome edge and the organ outlines sliding
together with the diaphragm, is the same. A moved state is a plain CT volume, so the
renderer, its blending in projection space and any projection cache take it unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config.case import Materials, Respiration
from ..errors import FluorosimError
from ..geometry import rotation_about
from .respiration import BreathState
from .volume import Volume


@dataclass(frozen=True)
class Rib:
    """One rigid rib: its voxels (HU and coverage) in a box of the grid, and its joint."""

    box: tuple[slice, slice, slice]         # (k, j, i) slices of the CT grid
    hu: np.ndarray                          # float32 HU in the box (premultiplied by alpha)
    alpha: np.ndarray                       # float32 coverage 0/1 in the box
    head_ct: np.ndarray                     # costovertebral joint (ct mm)
    side: int                               # +1 the patient's left (ct +x), -1 the right
    reach_mm: float                         # farthest voxel from the joint (mm)


#: Slices warped at a time (bounds the temporaries of a clinical CT to tens of MB).
SLAB_SLICES = 8


def rib_transform(head_ct, side: int, gamma_deg: float, lambda_deg: float) -> np.ndarray:
    """T_ct_moved_from_ct_rest (4x4) of a rib: lambda about -x (the front goes up), then gamma
    about the anteroposterior axis that lifts the side (-y on the left, +y on the right)."""
    R = (rotation_about((0.0, -float(side), 0.0), math.radians(gamma_deg))
         @ rotation_about((-1.0, 0.0, 0.0), math.radians(lambda_deg)))
    p = np.asarray(head_ct, float)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p - R @ p
    return T


def _label_mask(labels: np.ndarray | None, ids) -> np.ndarray | None:
    if labels is None or not ids:
        return None
    return np.isin(labels, np.asarray(ids, dtype=labels.dtype))


def _distance_near(mask: np.ndarray, reach_mm: float, sampling) -> np.ndarray:
    """float32 distance (mm) of each voxel from `mask`, computed only in the mask's bounding box
    grown by `reach_mm` (inf beyond it, and everywhere for an empty mask)."""
    from scipy import ndimage

    out = np.full(mask.shape, np.inf, np.float32)
    if not mask.any():
        return out
    lo_hi = [(int(ix.min()), int(ix.max())) for ix in np.nonzero(mask)]
    grow = [int(math.ceil(reach_mm / s)) for s in sampling]
    crop = tuple(slice(max(a - g, 0), min(b + g + 1, n)) for (a, b), g, n in zip(lo_hi, grow, mask.shape))
    out[crop] = ndimage.distance_transform_edt(~mask[crop], sampling=sampling)
    return out


def vertical_run_mm(mask: np.ndarray, dz_mm: float) -> np.ndarray:
    """float32 height (mm) of the unbroken vertical run (along the grid's k axis) of `mask`
    through each voxel of it; 0 outside the mask. Counted in column slabs to bound memory."""
    nz = mask.shape[0]
    out = np.zeros(mask.shape, np.float32)
    k = np.arange(nz, dtype=np.int32)[:, None]
    flat = mask.reshape(nz, -1)
    res = out.reshape(nz, -1)
    step = max(1, (1 << 22) // max(nz, 1))
    for c0 in range(0, flat.shape[1], step):
        m = flat[:, c0:c0 + step]
        if not m.any():
            continue
        # The last gap at or above each voxel and the first gap at or below it bound its run.
        start = np.maximum.accumulate(np.where(m, -1, k), axis=0)
        stop = np.minimum.accumulate(np.where(m, nz, k)[::-1], axis=0)[::-1]
        res[:, c0:c0 + step] = np.where(m, (stop - start - 1) * abs(dz_mm), 0.0)
    return out


def plates(bone: np.ndarray, dz_mm: float, spacing_xy, max_height_mm: float, widen_mm: float) -> np.ndarray:
    """The voxels of `bone` that belong to a plate standing taller than `max_height_mm` (a
    scapula, the sternum): bone widened by `widen_mm` in each axial slice, so that a thin plate
    leaning a little still stands in unbroken vertical runs, whose runs are taller than the
    limit, shrunk back by the same widening (a rib beside the plate keeps its voxels)."""
    from scipy import ndimage

    box = ndimage.find_objects(bone.astype(np.int8))
    out = np.zeros(bone.shape, bool)
    if not box or box[0] is None:
        return out
    grow = [int(round(widen_mm / s)) for s in (spacing_xy[1], spacing_xy[0])]
    sl = (box[0][0],) + tuple(slice(max(b.start - g, 0), min(b.stop + g, n))
                              for b, g, n in zip(box[0][1:], grow, bone.shape[1:]))
    wide = bone[sl].view(np.uint8)
    for axis, g in zip((1, 2), grow):
        if g > 0:
            wide = ndimage.maximum_filter1d(wide, 2 * g + 1, axis=axis)
    tall = (vertical_run_mm(wide.astype(bool), dz_mm) > max_height_mm).view(np.uint8)
    for axis, g in zip((1, 2), grow):
        if g > 0:
            tall = ndimage.minimum_filter1d(tall, 2 * g + 1, axis=axis)
    out[sl] = tall.astype(bool) & bone[sl]
    return out


class BreathingAnatomy:
    """A CT at end-expiration, split for breathing; `volume_at(state)` gives the moved CT."""

    def __init__(self, volume: Volume, params: Respiration, materials: Materials,
                 labels: np.ndarray | None = None, label_source: str = "label map"):
        from scipy import ndimage

        self.volume, self.params = volume, params
        T = np.asarray(volume.T_ct_from_voxel, float)
        self.T = T
        # The motion is along ct z; the grid's k axis must be that axis (axial slices).
        if not (abs(T[2, 0]) < 1e-6 and abs(T[2, 1]) < 1e-6 and abs(T[0, 2]) < 1e-6 and abs(T[1, 2]) < 1e-6
                and abs(T[2, 2]) > 1e-6):
            raise FluorosimError(f"{volume.source or 'the CT'}: breathing needs axial slices (the grid's third axis along "
                                 "the patient's head-foot axis); resample the CT or leave out `respiration:`")
        hu = np.asarray(volume.hu).astype(np.float32)
        if labels is not None and labels.shape != hu.shape:
            raise FluorosimError(f"{label_source}: label map of {labels.shape[::-1]} voxels, CT of {hu.shape[::-1]}; "
                                 "the label map must be on the CT's grid")
        nz, ny, nx = hu.shape
        self.shape = hu.shape
        sp = volume.spacing_mm
        self.dz = float(T[2, 2])                       # mm of ct z per k step (signed)
        z_k = T[2, 3] + self.dz * np.arange(nz)
        self.z_k = z_k
        role = (params.labels or {})
        bone = hu >= materials.bone_min_hu
        if materials.contrast_min_hu is not None:       # iodinated contrast is soft tissue that moves
            bone &= hu < materials.contrast_min_hu
        body = hu > materials.air_max_hu

        # --- lungs: labels, else the air inside the body (not connected to the sides of the grid)
        lungs = _label_mask(labels, role.get("lungs"))
        if lungs is None:
            air, n = ndimage.label(~body)
            sides = np.unique(np.concatenate([air[:, 0, :].ravel(), air[:, -1, :].ravel(),
                                              air[:, :, 0].ravel(), air[:, :, -1].ravel()]))
            sizes = ndimage.sum_labels(np.ones_like(air, np.int8), air, np.arange(n + 1))
            sizes[0] = 0
            sizes[sides] = 0
            biggest = sizes.max()
            keep = np.flatnonzero(sizes >= 0.3 * biggest) if biggest > 0 else np.zeros(0, np.intp)
            lungs = np.isin(air, keep) if len(keep) else np.zeros_like(body)
        if not lungs.any():
            raise FluorosimError(f"{volume.source or 'the CT'}: no lungs found for the breathing motion (no air inside "
                                 "the body); give a label map with `respiration.labels.lungs`")
        # --- the diaphragm: the lung bases (or the diaphragm's labels)
        dia = _label_mask(labels, role.get("diaphragm"))
        kk = np.arange(nz)[:, None, None]
        if dia is not None and dia.any():
            zs = z_k[np.nonzero(dia)[0]]
            self.dome_low_z, self.dome_top_z = float(zs.min()), float(zs.max())
        else:
            # Lowest lung voxel of each column: the diaphragm's surface seen from above.
            cols = lungs.any(axis=0)
            lowest_k = np.where(lungs, kk, nz if self.dz > 0 else -1)
            lowest_k = lowest_k.min(axis=0) if self.dz > 0 else lowest_k.max(axis=0)
            base_z = z_k[np.clip(lowest_k[cols], 0, nz - 1)]
            # The dome's top from the columns of deep lung only: at the lungs' front, back and
            # medial edges the base rises with the lung's own outline, not the diaphragm.
            depth = lungs.sum(axis=0)[cols]
            deep = base_z[depth >= 0.4 * depth.max()]
            self.dome_low_z, self.dome_top_z = float(np.percentile(base_z, 0.5)), float(np.percentile(deep, 98))
        lz = z_k[np.nonzero(lungs.any(axis=(1, 2)))[0]]
        self.lung_top_z = float(lz.max())
        # --- lateral footprint of what moves: the lungs (and liver) seen along z, softened
        foot = lungs.any(axis=0)
        liver = _label_mask(labels, role.get("liver"))
        if liver is not None:
            foot |= liver.any(axis=0)
        blur = params.lateral_blur_mm
        lateral = foot.astype(np.float32)
        if blur > 0:
            lateral = ndimage.gaussian_filter(lateral, (blur / sp[1], blur / sp[0]))
            lateral = np.clip(lateral / 0.5, 0.0, 1.0)      # 1 inside, half way at the footprint's edge
        self.lateral = np.asarray(lateral, np.float32)

        # --- the spine and the ribs
        spine = _label_mask(labels, role.get("spine"))
        i_x = T[0, 3] + T[0, 0] * np.arange(nx)
        j_y = T[1, 3] + T[1, 1] * np.arange(ny)
        xc = float((body.sum(axis=(0, 1)) * i_x).sum() / max(body.sum(), 1))
        yc = float((body.sum(axis=(0, 2)) * j_y).sum() / max(body.sum(), 1))
        self.midline_x = xc
        if spine is None:
            band = (np.abs(i_x - xc) <= params.spine_half_width_mm)[None, None, :] & (j_y >= yc)[None, :, None]
            spine = bone & band
        rib_mask = _label_mask(labels, role.get("ribs"))
        from_labels = rib_mask is not None
        # Distance to the spine only near it (a whole-CT distance map costs seconds on a clinical CT).
        far = None
        if spine.any():
            reach = params.rib_head_max_mm if from_labels or params.rib_pleura_max_mm is None else max(
                params.rib_head_max_mm, params.rib_neck_mm)
            far = _distance_near(spine, reach + 2 * float(max(abs(self.dz), *sp)), (abs(self.dz), sp[1], sp[0]))
        if rib_mask is None:
            rib_mask = bone & ~spine
            # Ribs lie between the lowest ribs (below the diaphragm's lowest point) and the apices.
            in_thorax = (z_k >= self.dome_low_z - 80.0) & (z_k <= self.lung_top_z + 10.0)
            rib_mask &= in_thorax[:, None, None]
            if params.rib_max_height_mm is not None:
                rib_mask &= ~plates(rib_mask, self.dz, sp, params.rib_max_height_mm, params.rib_plate_widen_mm)
            if params.rib_pleura_max_mm is not None:
                rib_mask &= self._lining(lungs, far, params, j_y >= yc, sp)
        pieces, n = ndimage.label(rib_mask)
        self.ribs: list[Rib] = []
        moving = np.zeros(hu.shape, bool)
        objects = ndimage.find_objects(pieces)
        for idx, sl in enumerate(objects, start=1):
            if sl is None:
                continue
            # One empty voxel round the piece, so interpolation at its faces blends toward nothing.
            sl = tuple(slice(max(a.start - 1, 0), min(a.stop + 1, n)) for a, n in zip(sl, hu.shape))
            mine = pieces[sl] == idx
            if mine.sum() < 8:
                continue
            ks, js, is_ = np.nonzero(mine)
            pts = np.stack([is_ + sl[2].start, js + sl[1].start, ks + sl[0].start, np.ones_like(ks)]).astype(float)
            ct = (T @ pts)[:3]
            if far is not None:
                d = far[sl][mine]
                nearest = int(np.argmin(d))
                if not from_labels and d[nearest] > params.rib_head_max_mm:
                    continue
            else:
                nearest = int(np.argmin(np.abs(ct[0] - xc)))
            head = ct[:, nearest]
            side = 1 if float(np.mean(ct[0])) >= xc else -1
            reach = float(np.linalg.norm(ct - head[:, None], axis=0).max())
            if not from_labels and (reach < params.rib_min_length_mm
                                    or head[2] < self.dome_low_z - params.rib_below_dome_mm):
                continue
            alpha = mine.astype(np.float32)
            self.ribs.append(Rib(sl, hu[sl] * alpha, alpha, head, side, reach))
            moving[sl] |= mine
        self.still = bone & ~moving
        self.still_hu = hu[self.still]
        soft = hu.copy()
        soft[bone] = params.bone_fill_hu
        self.soft = soft

    def _lining(self, lungs, far, params: Respiration, posterior_j, sp) -> np.ndarray:
        """Where rib bone may be found from HU when the scapulae touch the ribs: within
        rib_pleura_max_mm of the lungs or rib_neck_mm of the spine; anywhere in front of the
        body's centre or below the domes' tops, where no scapula lies on the cage (the front of
        the upper ribs and the lowest ribs run farther from the lungs)."""
        assert params.rib_pleura_max_mm is not None
        sampling = (abs(self.dz), sp[1], sp[0])
        lining = _distance_near(lungs, params.rib_pleura_max_mm + 2 * float(max(sampling)),
                                sampling) <= params.rib_pleura_max_mm
        if far is not None:
            lining |= far <= params.rib_neck_mm
        lining |= ~np.asarray(posterior_j)[None, :, None]
        lining |= (self.z_k < self.dome_top_z)[:, None, None]
        return lining

    # -- the soft-tissue field ---------------------------------------------------------
    def weight_z(self, z):
        """Share (0-1) of the tendon's descent that tissue at height z (ct mm) moves by."""
        z = np.asarray(z, float)
        top, low = self.dome_top_z, self.dome_low_z
        above = np.clip((self.lung_top_z - z) / max(self.lung_top_z - top, 1e-6), 0.0, 1.0)
        below = np.clip(1.0 - (low - z) / self.params.abdomen_falloff_mm, 0.0, 1.0)
        return np.where(z > top, above, np.where(z < low, below, 1.0))

    def displacement_mm(self, points_ct, descent_mm: float) -> np.ndarray:
        """(n, 3) displacement (ct mm) of soft tissue at `points_ct` (n, 3) for a tendon descent (mm)."""
        p = np.atleast_2d(np.asarray(points_ct, float))
        idx = np.linalg.solve(self.T, np.c_[p, np.ones(len(p))].T)[:3]
        i = np.clip(np.rint(idx[0]).astype(int), 0, self.shape[2] - 1)
        j = np.clip(np.rint(idx[1]).astype(int), 0, self.shape[1] - 1)
        out = np.zeros_like(p)
        out[:, 2] = -descent_mm * self.weight_z(p[:, 2]) * self.lateral[j, i]
        return out

    def soft_of(self, stage: Volume) -> np.ndarray:
        """The soft tissue of another volume on the same grid that differs from this CT only in
        soft tissue (a contrast study's later stage): this CT's soft layer with its changed voxels."""
        hu = np.asarray(stage.hu)
        if hu.shape != self.shape:
            raise FluorosimError(f"{stage.source}: a stage of {stage.shape_xyz} voxels, the breathing CT has "
                                 f"{self.shape[::-1]}; every stage must share one grid")
        changed = hu != np.asarray(self.volume.hu)
        soft = self.soft.copy()
        soft[changed] = hu[changed]
        return soft

    def _soft_at(self, descent_mm: float, soft_layer: np.ndarray | None = None) -> np.ndarray:
        base = self.soft if soft_layer is None else soft_layer
        if descent_mm == 0:
            return base.copy()
        nz = self.shape[0]
        w = self.weight_z(self.z_k).astype(np.float32)
        ks = np.flatnonzero(w > 0)
        out = base.copy()
        if ks.size == 0:
            return out
        k0, k1 = int(ks[0]), int(ks[-1]) + 1
        js, is_ = np.nonzero(self.lateral > 0)
        if js.size == 0:
            return out
        cols = (slice(int(js.min()), int(js.max()) + 1), slice(int(is_.min()), int(is_.max()) + 1))
        lateral = self.lateral[cols][None]
        soft = base[:, cols[0], cols[1]]
        # Tissue moves down by D w m: the voxel at z shows what was at z + D w m (w varies
        # slowly). In slabs, so the temporaries of a clinical CT stay small.
        for s0 in range(k0, k1, SLAB_SLICES):
            s1 = min(s0 + SLAB_SLICES, k1)
            src = np.arange(s0, s1, dtype=np.float32)[:, None, None] + (np.float32(descent_mm / self.dz) * w[s0:s1, None, None]) * lateral
            np.clip(src, 0, nz - 1, out=src)
            lo = np.floor(src).astype(np.int32)
            f = src - lo
            hi = np.minimum(lo + 1, nz - 1)
            a = np.take_along_axis(soft, lo, axis=0)
            b = np.take_along_axis(soft, hi, axis=0)
            out[s0:s1, cols[0], cols[1]] = a + f * (b - a)
        return out

    # -- the whole moved CT ------------------------------------------------------------
    def hu_at(self, gamma_deg: float, lambda_deg: float, descent_mm: float,
              soft_layer: np.ndarray | None = None) -> np.ndarray:
        """float32 HU (nz, ny, nx) of the CT with the ribs turned and the soft tissue displaced
        (`soft_layer`: another stage's soft tissue from `soft_of`, else this CT's)."""
        from scipy import ndimage

        out = self._soft_at(descent_mm, soft_layer)
        Tinv = np.linalg.inv(self.T)
        sp = self.volume.spacing_mm
        nz, ny, nx = self.shape
        for rib in self.ribs:
            if gamma_deg == 0 and lambda_deg == 0:
                out[rib.box] = out[rib.box] * (1 - rib.alpha) + rib.hu
                continue
            M = rib_transform(rib.head_ct, rib.side, gamma_deg, lambda_deg)
            # Output box: the rib's box grown by the farthest any of its voxels can move.
            move = rib.reach_mm * math.radians(abs(gamma_deg) + abs(lambda_deg)) + 2 * sp.max()
            grow = [int(math.ceil(move / s)) for s in (abs(self.dz), sp[1], sp[0])]
            box = tuple(slice(max(s.start - g, 0), min(s.stop + g, n)) for s, g, n in zip(rib.box, grow, (nz, ny, nx)))
            kk, jj, ii = np.meshgrid(*[np.arange(s.start, s.stop, dtype=np.float64) for s in box], indexing="ij")
            pts = np.stack([ii.ravel(), jj.ravel(), kk.ravel(), np.ones(ii.size)])
            # Where each output voxel's content came from: T^-1 M^-1 T, in grid indices.
            src = (Tinv @ np.linalg.inv(M) @ self.T @ pts)[:3]
            coords = np.stack([src[2] - rib.box[0].start, src[1] - rib.box[1].start, src[0] - rib.box[2].start])
            a = ndimage.map_coordinates(rib.alpha, coords, order=1, mode="constant", cval=0.0).reshape(ii.shape)
            c = ndimage.map_coordinates(rib.hu, coords, order=1, mode="constant", cval=0.0).reshape(ii.shape)
            out[box] = out[box] * (1 - a) + c
        out[self.still] = self.still_hu
        return out

    def volume_at(self, state: BreathState, soft_layer: np.ndarray | None = None) -> Volume:
        """The moved CT for a breath state, as a Volume (int16 HU) on the CT's grid."""
        hu = self.hu_at(state.gamma_deg, state.lambda_deg, state.descent_mm, soft_layer)
        return Volume(np.clip(np.rint(hu), -1024, 32767).astype(np.int16), self.volume.T_ct_from_voxel,
                      source=f"{self.volume.source} breathing ({state.excursion:.2f} of the breath)")


def load_labels(case_path: Path, params: Respiration, ct: Volume) -> np.ndarray | None:
    """The case's label map as an integer array on the CT's grid, or None when the case gives none."""
    from ..config.loading import resolve
    from .label_points import label_map_on_grid

    if not params.label_map:
        return None
    return label_map_on_grid(resolve(case_path, params.label_map), ct)
