"""Composite-marker calibration: where each marker sits relative to the root marker.

The seed paper's method (section 2.2.1): every frame that shows two or more markers gives,
for each co-visible pair (a, b), the relative transform T_a_from_b = inv(T_wc_a) @ T_wc_b.
The edge keeps its transform only while its quality improves; edge quality is the worse
(larger) of the two markers' ray-to-normal angles. When the graph connects every marker
to the root, each marker's transform to the root is composed along the shortest path
(Dijkstra).

After that, `refine()` adjusts the whole layout and every stored frame's phantom pose
together to minimise the corner reprojection error over all frames (a bundle adjustment):
the graph alone inherits each single-marker pose's depth error (millimetres for a 50 mm
marker at half a metre), the adjustment averages it away over hundreds of views.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from ..geometry import invert, make_transform
from .markers import distort, marker_corners, marker_pose

#: Each hop adds error, so a path's length counts hops as well as their angles: one hop
#: weighs as much as this many degrees of edge angle.
HOP_COST_DEG = 10.0
#: Markers seen more obliquely than this (ray-to-normal angle, degrees) are left out of the
#: graph: beyond it their corners are off by pixels.
GRAPH_MAX_ANGLE_DEG = 75.0
#: The bundle adjustment is stricter: its observations stop at this angle (degrees); beyond
#: about 70 degrees the corner errors stall it. A marker seen only more obliquely keeps its
#: transform from the graph.
ADJUST_MAX_ANGLE_DEG = 65.0
#: A marker whose corners miss by more than this after adjustment (RMS, pixels) is an outlier in that frame.
OUTLIER_PX = 1.0


@dataclass
class Edge:
    quality_deg: float          # the worse ray-to-normal angle of the two markers (smaller is better)
    T_a_from_b: np.ndarray


@dataclass
class CompositeCalibration:
    marker_ids: list[int]
    root_id: int
    T_phantom_from_root: np.ndarray
    size_mm: float
    K: np.ndarray
    dist: np.ndarray
    max_frames: int = 400
    edges: dict[tuple[int, int], Edge] = field(default_factory=dict)
    seen: set[int] = field(default_factory=set)
    frames: list[dict[int, np.ndarray]] = field(default_factory=list)
    frames_used: int = 0

    def add(self, detected: dict[int, np.ndarray]) -> None:
        """Take one frame's detected corners {marker id: (4, 2) pixels}."""
        detected = {i: c for i, c in detected.items() if i in self.marker_ids}
        poses = {}
        for i, c in detected.items():
            p = marker_pose(i, c, self.size_mm, self.K, self.dist)
            if p is not None and p.angle_deg <= GRAPH_MAX_ANGLE_DEG:
                poses[i] = p
        self.seen.update(poses)
        if len(poses) < 2:
            return
        self.frames_used += 1
        clear = {i: detected[i] for i, p in poses.items() if p.angle_deg <= ADJUST_MAX_ANGLE_DEG}
        if len(clear) >= 2 and len(self.frames) < self.max_frames:
            self.frames.append(clear)
        ids = sorted(poses)
        for k, a in enumerate(ids):
            for b in ids[k + 1:]:
                q = max(poses[a].angle_deg, poses[b].angle_deg)
                old = self.edges.get((a, b))
                if old is None or q < old.quality_deg:
                    T = invert(poses[a].T_webcam_from_marker) @ poses[b].T_webcam_from_marker
                    self.edges[(a, b)] = Edge(q, T)

    def _neighbours(self):
        graph: dict[int, list[tuple[int, float, np.ndarray]]] = {i: [] for i in self.marker_ids}
        for (a, b), e in self.edges.items():
            w = e.quality_deg + HOP_COST_DEG
            graph[a].append((b, w, e.T_a_from_b))
            graph[b].append((a, w, invert(e.T_a_from_b)))
        return graph

    def shortest_paths(self) -> dict[int, np.ndarray]:
        """T_root_from_marker of every marker reachable from the root, composed along Dijkstra paths."""
        graph = self._neighbours()
        best = {self.root_id: (0.0, np.eye(4))}
        heap = [(0.0, self.root_id)]
        done = set()
        while heap:
            d, a = heapq.heappop(heap)
            if a in done:
                continue
            done.add(a)
            for b, w, T_a_from_b in graph[a]:
                nd = d + w
                if b not in best or nd < best[b][0]:
                    best[b] = (nd, best[a][1] @ T_a_from_b)
                    heapq.heappush(heap, (nd, b))
        return {i: T for i, (_, T) in best.items()}

    def missing(self) -> list[int]:
        """Markers not yet connected to the root."""
        reached = self.shortest_paths()
        return [i for i in self.marker_ids if i not in reached]

    def connected(self) -> bool:
        return not self.missing()

    def layout(self) -> dict[int, np.ndarray]:
        """T_phantom_from_marker of every connected marker, from the graph alone."""
        return {i: self.T_phantom_from_root @ T for i, T in self.shortest_paths().items()}

    def refine(self, T_root_from_marker: dict[int, np.ndarray] | None = None) -> tuple[dict[int, np.ndarray], float]:
        """Bundle-adjusted T_phantom_from_marker of every connected marker and the final RMS (pixels).

        A marker whose corners in one frame still miss by more than OUTLIER_PX after the first
        adjustment (a misread corner, a marker seen at a grazing angle) is dropped from that frame
        and the adjustment is run again.
        """
        start = T_root_from_marker or self.shortest_paths()
        corners = marker_corners(self.size_mm)
        # Initial phantom (root) pose of each frame: PnP over its markers with the graph layout.
        frames, poses = [], []
        for det in self.frames:
            det = {i: c for i, c in det.items() if i in start}
            if len(det) < 2:
                continue
            obj = np.concatenate([corners @ start[i][:3, :3].T + start[i][:3, 3] for i in det])
            T = _pnp(obj, np.concatenate([det[i] for i in det]), self.K, self.dist)
            if T is not None:
                frames.append(det)
                poses.append(T)
        if not frames:
            return {self.root_id: self.T_phantom_from_root.copy()}, float("nan")
        layout = start
        for _ in range(2):
            layout, poses, errors = self._adjust(frames, layout, poses)
            kept = [{i: c for i, c in det.items() if errors[f][i] <= OUTLIER_PX} for f, det in enumerate(frames)]
            if all(len(k) == len(d) for k, d in zip(kept, frames)):
                break
            keep = [f for f, k in enumerate(kept) if len(k) >= 2]
            frames, poses = [kept[f] for f in keep], [poses[f] for f in keep]
        rms = float(np.sqrt(np.mean([e ** 2 for f in errors for e in f.values()])))
        return {i: self.T_phantom_from_root @ layout.get(i, start[i]) for i in start}, rms

    def _adjust(self, frames, start, poses0):
        """One bundle adjustment: (T_root_from_marker, T_webcam_from_root per frame, per frame {id: RMS px})."""
        markers = sorted({i for det in frames for i in det} - {self.root_id})
        index = {m: k for k, m in enumerate(markers)}
        corners = marker_corners(self.size_mm)
        nm, nf = len(markers), len(frames)
        # Observations: (frame index, marker index or -1 for the root, corner k) -> pixel.
        f_idx, m_idx, pts, img = [], [], [], []
        for f, det in enumerate(frames):
            for i, c in det.items():
                f_idx += [f] * 4
                m_idx += [index.get(i, -1)] * 4
                pts.append(corners)
                img.append(c)
        f_idx, m_idx = np.array(f_idx), np.array(m_idx)
        pts, img = np.concatenate(pts), np.concatenate(img)

        def unpack(x):
            return x[:6 * nm].reshape(nm, 6), x[6 * nm:].reshape(nf, 6)

        def residuals(x):
            mk, fr = unpack(x)
            Rm = Rotation.from_rotvec(np.vstack([mk[:, :3], np.zeros((1, 3))]))
            tm = np.vstack([mk[:, 3:], np.zeros((1, 3))])
            p = Rm[m_idx].apply(pts) + tm[m_idx]                  # root frame (the root is the last row)
            p = Rotation.from_rotvec(fr[:, :3])[f_idx].apply(p) + fr[f_idx, 3:]
            return (distort(p[:, :2] / p[:, 2:3], self.K, self.dist) - img).ravel()

        def params(T):
            return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])

        x0 = np.concatenate([params(start[m]) for m in markers] + [params(T) for T in poses0])
        # Each corner's two residuals depend on its frame's 6 parameters and its marker's 6 (none for the root).
        rr, cc = [], []
        has = m_idx >= 0
        for axis in (0, 1):
            r = 2 * np.arange(len(pts)) + axis
            for k in range(6):
                rr += [r, r[has]]
                cc += [6 * nm + 6 * f_idx + k, 6 * m_idx[has] + k]
        rr, cc = np.concatenate(rr), np.concatenate(cc)
        sparsity = coo_matrix((np.ones(rr.size, np.uint8), (rr, cc)), shape=(2 * len(pts), x0.size)).tocsr()
        result = least_squares(residuals, x0, jac_sparsity=sparsity, method="trf", x_scale="jac",
                               loss="huber", f_scale=1.0, max_nfev=100)
        mk, fr = unpack(result.x)
        layout = {self.root_id: np.eye(4)}
        for m, k in index.items():
            layout[m] = make_transform(Rotation.from_rotvec(mk[k, :3]).as_matrix(), mk[k, 3:])
        poses = [make_transform(Rotation.from_rotvec(fr[f, :3]).as_matrix(), fr[f, 3:]) for f in range(nf)]
        d2 = np.sum(residuals(result.x).reshape(-1, 2) ** 2, axis=1).reshape(-1, 4).mean(axis=1)
        errors: list[dict[int, float]] = [{} for _ in range(nf)]
        obs = 0
        for f, det in enumerate(frames):
            for i in det:
                errors[f][i] = float(np.sqrt(d2[obs]))
                obs += 1
        return layout, poses, errors


def _pnp(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray | None:
    ok, rvec, tvec = cv2.solvePnP(obj, img.reshape(-1, 1, 2), K, dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img.reshape(-1, 1, 2), K, dist, rvec, tvec)
    return make_transform(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
