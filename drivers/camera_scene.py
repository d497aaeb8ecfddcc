"""The synthetic webcam's scene: a box with printed ArUco markers, imaged through a pinhole
camera with OpenCV distortion, lighting, optical blur, motion blur and sensor noise.

`SyntheticCamera` (in `camera`) plays it along a trajectory in place of the webcam; the
tracking benchmarks and tests render single views with it. It takes plain numbers (this
package knows nothing of the appliance's profiles).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

#: Box faces as (outward normal, in-face axis u, in-face axis v) in the box frame; u x v = normal.
_FACES = [((0, 0, 1), (1, 0, 0), (0, 1, 0)), ((0, 0, -1), (1, 0, 0), (0, -1, 0)),
          ((0, 1, 0), (0, 0, 1), (1, 0, 0)), ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
          ((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((-1, 0, 0), (0, 0, 1), (0, 1, 0))]

#: The sensor noise pool is this much wider and taller than the frame (pixels): the range of a
#: frame's random offset into it. Not a camera property, so not a setting: any value above a few
#: pixels gives frames whose noise no tracker can tell from fresh draws.
_NOISE_PAD_PX = 64
#: Bands of the pool drawn anew per frame, one each frame: the pool is all new every this many frames.
_NOISE_BANDS = 16


@dataclass
class RenderSettings:
    """How the synthetic webcam images its scene; defaults mimic a 720p USB webcam indoors."""

    exposure_s: float = 1.0 / 60.0      # shutter time: motion during it smears the image (s)
    blur_sigma_px: float = 0.7          # optical blur of lens and demosaicing, Gaussian sigma (pixels)
    antialias_px: float = 0.5           # prefilter of the printed texture before sampling, Gaussian sigma (pixels)
    noise_sigma: float = 2.0            # sensor noise, Gaussian sigma (grey levels of 255)
    light_dir: tuple = (-0.3, -0.6, -1.0)  # direction from the scene toward the light, webcam frame
    ambient: float = 0.45               # share of light that does not depend on the surface angle
    paper_white: float = 235.0          # grey level of the printed paper under full light
    ink_black: float = 25.0             # grey level of the printed black under full light
    box_grey: float = 150.0             # grey level of the box's bare surface under full light
    background: float = 70.0            # grey level of the table and room behind the box
    margin_cells: float = 1.0           # white paper margin around each marker (marker cells)
    jpeg_quality: int | None = None     # MJPG webcams: compress each frame at this JPEG quality (1-100), None: raw


@dataclass
class TexturedQuad:
    """A flat print: its texture's corners sit at (+-half_w, +-half_h) in its own frame (mm), x right, y up."""

    T_box_from_quad: np.ndarray
    half_w_mm: float
    half_h_mm: float
    textures: list[np.ndarray]          # the same print at several resolutions, finest last


def _covers(outer: tuple[int, int, int, int], inner: tuple[int, int, int, int]) -> bool:
    """Whether the pixel box `outer` (x0, y0, x1, y1) holds all of `inner`."""
    return outer[0] <= inner[0] and outer[1] <= inner[1] and outer[2] >= inner[2] and outer[3] >= inner[3]


def marker_textures(dictionary: str, marker_id: int, margin_cells: float = 1.0,
                    paper: float = 1.0, ink: float = 0.0) -> list[np.ndarray]:
    """Float32 prints of one ArUco marker with its white margin, at 4, 8, 16 and 32 pixels per cell."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    cells = d.markerSize + 2
    out = []
    for ppc in (4, 8, 16, 32):
        img = cv2.aruco.generateImageMarker(d, marker_id, cells * ppc, borderBits=1)
        m = int(round(margin_cells * ppc))
        img = cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255)
        out.append(np.where(img > 127, paper, ink).astype(np.float32))
    return out


class SceneRenderer:
    """Renders a box with printed squares through a pinhole camera with OpenCV distortion."""

    def __init__(self, K: np.ndarray, dist: np.ndarray | Sequence[float], width: int, height: int,
                 box_mm: tuple | None, quads: list[TexturedQuad], settings: RenderSettings | None = None,
                 seed: int | None = None) -> None:
        self.K = np.asarray(K, dtype=np.float64)
        self.dist = np.asarray(dist, dtype=np.float64).reshape(-1)
        self.width, self.height = int(width), int(height)
        self.box_mm = None if box_mm is None else tuple(float(v) for v in box_mm)
        self.quads = quads
        self.s = settings or RenderSettings()
        self.rng = np.random.default_rng(seed)
        light = np.asarray(self.s.light_dir, dtype=np.float64)
        self.light = light / np.linalg.norm(light)
        yy, xx = np.mgrid[0:self.height, 0:self.width].astype(np.float32)
        # A soft gradient so the background is not a flat field a detector could key on.
        self.backdrop = (self.s.background * (0.8 + 0.4 * xx / self.width) * (0.9 + 0.2 * yy / self.height)).astype(np.float32)
        self._maps = None
        self._last_key: bytes | None = None         # the pose of the last frame drawn, and its image
        self._last_clean = self.backdrop
        # The backdrop through the lens, and the image the box is pasted into (see _optics).
        self._still = self._blur(self.backdrop, None)
        self._canvas = self._still.copy()
        self._pasted: tuple[int, int, int, int] | None = None   # where the last box went (x0, y0, x1, y1)
        self._pool: np.ndarray | None = None        # the sensor's noise pool, see _sensor
        self._noise_band = 0
        if np.any(self.dist != 0):
            # For each output (distorted) pixel, the ideal pinhole pixel it sees.
            pts = np.stack([xx.ravel(), yy.ravel()], axis=1).reshape(-1, 1, 2).astype(np.float64)
            ideal = cv2.undistortPoints(pts, self.K, self.dist, R=None, P=self.K,
                                        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9))
            ideal = ideal.reshape(self.height, self.width, 2).astype(np.float32)
            self._maps = cv2.convertMaps(ideal[..., 0], ideal[..., 1], cv2.CV_16SC2)

    # Pinhole projection of camera-frame points; the distortion is applied to the whole image later.
    def _project(self, pts_cam: np.ndarray) -> np.ndarray:
        uvw = pts_cam @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3]

    def _shade(self, normal_cam: np.ndarray) -> float:
        return self.s.ambient + (1.0 - self.s.ambient) * max(0.0, float(normal_cam @ self.light))

    def render(self, T_cam_from_box: np.ndarray, exposure: tuple | None = None) -> np.ndarray:
        """A uint8 grey image of the scene at `T_cam_from_box` (mm).

        `exposure` = (T at shutter open, T at shutter close) smears the image along the motion.
        A frame at the pose (and motion) of the one before reuses its drawing and lens, with new
        sensor noise: the still C-arm of a demo's holds then costs the appliance what a real
        webcam does (its frames cost nothing to make), not a scene render each time.
        """
        key = T_cam_from_box.tobytes() + (b"" if exposure is None else exposure[0].tobytes() + exposure[1].tobytes())
        if key != self._last_key:
            self._last_key, self._last_clean = key, self._optics(T_cam_from_box, exposure)
        return self._sensor(self._last_clean)

    def _optics(self, T_cam_from_box: np.ndarray, exposure: tuple | None) -> np.ndarray:
        """The scene through the lens, before the sensor (float32 grey levels).

        Only the part of the image the box can reach is drawn and blurred, over a backdrop
        blurred once: the rest is the same gradient every frame. (Along the demo path the box's
        bounds fill most of the frame, so there this saves a copy, not the blur; it pays when
        the box is farther off.) The part is drawn with twice the blurs' reach around the
        box and pasted with one reach, so every pasted pixel saw all the neighbours it sees in a
        whole frame; outside it the backdrop misses only the motion smear, which leaves a linear
        gradient as it was. Distortion moves every pixel, so it still maps the whole frame.
        """
        kernel = self._motion_kernel(exposure)
        reach = (kernel.shape[0] - 1) // 2 if kernel is not None else 0
        if self.s.blur_sigma_px > 0:
            reach += int(np.ceil(4 * self.s.blur_sigma_px)) + 1   # OpenCV's float kernel spans 4 sigma
        canvas = self._canvas
        extent = self._extent(T_cam_from_box)
        paste = None if extent is None else self._grown(extent, reach)
        if self._pasted is not None and not (paste is not None and _covers(paste, self._pasted)):
            x0, y0, x1, y1 = self._pasted        # the last box, where this one will not paint over it
            canvas[y0:y1, x0:x1] = self._still[y0:y1, x0:x1]
        self._pasted = None
        if extent is not None and paste is not None:
            cx0, cy0, cx1, cy1 = self._grown(extent, 2 * reach)
            part: np.ndarray = self.backdrop[cy0:cy1, cx0:cx1].copy()
            self._draw(part, (cx0, cy0), T_cam_from_box)
            part = self._blur(part, kernel)
            x0, y0, x1, y1 = self._pasted = paste
            canvas[y0:y1, x0:x1] = part[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0]
        if self._maps is not None:
            return cv2.remap(canvas, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return canvas

    def _grown(self, extent: tuple[int, int, int, int], by: int) -> tuple[int, int, int, int]:
        """`extent` (x0, y0, x1, y1) grown by `by` pixels on every side, within the image."""
        x0, y0, x1, y1 = extent
        return max(x0 - by, 0), max(y0 - by, 0), min(x1 + by, self.width), min(y1 + by, self.height)

    def _extent(self, T_cam_from_box: np.ndarray) -> tuple[int, int, int, int] | None:
        """The pixels (x0, y0, x1, y1) the box and its prints can touch, seen or not; None: none."""
        square = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], dtype=np.float64)
        pts = [(square * [q.half_w_mm, q.half_h_mm, 0]) @ q.T_box_from_quad[:3, :3].T + q.T_box_from_quad[:3, 3]
               for q in self.quads]
        if self.box_mm is not None:
            half = np.array(self.box_mm) / 2
            pts.append(np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * half)
        if not pts:
            return None
        cam = np.concatenate(pts) @ T_cam_from_box[:3, :3].T + T_cam_from_box[:3, 3]
        if np.any(cam[:, 2] < 1.0):
            return 0, 0, self.width, self.height     # a corner behind the lens: draw the whole frame
        px = self._project(cam)
        # The same bounds _draw_quad clips a print to, and a pixel of antialiasing round a face.
        x0, y0 = np.floor(px.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, self.width), min(y1, self.height)
        return None if x1 <= x0 or y1 <= y0 else (int(x0), int(y0), int(x1), int(y1))

    def _draw(self, img: np.ndarray, origin: tuple[int, int], T_cam_from_box: np.ndarray) -> None:
        """Draws the box and its prints into `img`, whose top left pixel is `origin` (x, y) of the frame."""
        R, t = T_cam_from_box[:3, :3], T_cam_from_box[:3, 3]
        half: np.ndarray = np.zeros(3) if self.box_mm is None else np.array(self.box_mm) / 2
        for face in (_FACES if self.box_mm is not None else ()):
            n, u, v = (np.asarray(a, dtype=np.float64) for a in face)
            centre = n * half
            n_cam = R @ n
            c_cam = R @ centre + t
            if n_cam @ c_cam >= 0:       # facing away from the camera
                continue
            hu, hv = np.abs(u) @ half, np.abs(v) @ half
            corners = np.array([centre + a * hu * u + b * hv * v for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
            cam = corners @ R.T + t
            if np.any(cam[:, 2] < 1.0):
                continue
            # Whole pixels of offset in 1/16 pixel fixed point: the same edges as in a whole frame.
            px = np.round(self._project(cam) * 16).astype(np.int32) - 16 * np.asarray(origin, np.int32)
            shade = self._shade(n_cam)
            cv2.fillConvexPoly(img, px, self.s.box_grey * shade, lineType=cv2.LINE_AA, shift=4)
        for q in self.quads:
            self._draw_quad(img, origin, T_cam_from_box @ q.T_box_from_quad, q)

    def _draw_quad(self, img: np.ndarray, origin: tuple[int, int], T_cam_from_quad: np.ndarray, q: TexturedQuad) -> None:
        R, t = T_cam_from_quad[:3, :3], T_cam_from_quad[:3, 3]
        n_cam = R[:, 2]
        if n_cam @ t >= 0 or t[2] < 1.0:
            return
        w, h = q.half_w_mm, q.half_h_mm
        corners = np.array([[-w, h, 0], [w, h, 0], [w, -h, 0], [-w, -h, 0]], dtype=np.float64)
        cam = corners @ R.T + t
        if np.any(cam[:, 2] < 1.0):
            return
        px = self._project(cam)
        x0, y0 = np.floor(px.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 2
        ox, oy = origin
        x0, y0, x1, y1 = max(x0, ox), max(y0, oy), min(x1, ox + img.shape[1]), min(y1, oy + img.shape[0])
        if x1 <= x0 or y1 <= y0:
            return
        # Pick the coarsest print that still has at least one texel per screen pixel (a cheap mipmap).
        side_u = (np.linalg.norm(px[1] - px[0]) + np.linalg.norm(px[2] - px[3])) / 2
        side_v = (np.linalg.norm(px[3] - px[0]) + np.linalg.norm(px[2] - px[1])) / 2
        tex = next((tx for tx in q.textures if tx.shape[1] >= side_u and tx.shape[0] >= side_v), q.textures[-1])
        nv, nu = tex.shape
        # Texel (i, j) centre at (j, i); its edge at -0.5 is the quad's left/top edge.
        tex_corners = np.array([[-0.5, -0.5], [nu - 0.5, -0.5], [nu - 0.5, nv - 0.5], [-0.5, nv - 0.5]], dtype=np.float32)
        H = cv2.getPerspectiveTransform(tex_corners, (px - [x0, y0]).astype(np.float32))
        shade = self._shade(n_cam)
        lo, hi = self.s.ink_black * shade, self.s.paper_white * shade
        region = img[y0 - oy:y1 - oy, x0 - ox:x1 - ox]
        # Point-sampling a sharp print quantises its edges to whole pixels (a quarter-pixel bias in
        # marker corners); band-limiting it first to half a screen pixel makes every sample exact.
        sx = self.s.antialias_px * nu / max(side_u, 1.0)
        sy = self.s.antialias_px * nv / max(side_v, 1.0)
        if self.s.antialias_px > 0:
            tex = cv2.GaussianBlur(tex, (0, 0), sx, sigmaY=sy, borderType=cv2.BORDER_REPLICATE)
        printed = tex * (hi - lo) + lo
        cv2.warpPerspective(printed, H, (x1 - x0, y1 - y0), dst=region, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_TRANSPARENT)

    def _motion_kernel(self, exposure: tuple | None) -> np.ndarray | None:
        """Motion blur: a centred line kernel along the image motion of the box centre during the exposure."""
        if exposure is None:
            return None
        p = self._project(np.array([exposure[1][:3, 3], exposure[0][:3, 3]]))
        d = p[0] - p[1]
        length = float(np.hypot(*d))
        if length < 1.0:
            return None
        k = int(np.ceil(length)) | 1
        kernel = np.zeros((k, k), np.float32)
        c = (k - 1) / 2
        for s in np.linspace(-0.5, 0.5, 4 * k):
            kernel[int(round(c + s * d[1])), int(round(c + s * d[0]))] += 1.0
        kernel /= kernel.sum()
        return kernel

    def _blur(self, img: np.ndarray, kernel: np.ndarray | None) -> np.ndarray:
        """Motion blur over the exposure and the lens's blur (its distortion is applied in _optics)."""
        if kernel is not None:
            img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        if self.s.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.s.blur_sigma_px)
        return img

    def _sensor(self, img: np.ndarray) -> np.ndarray:
        """The sensor's noise, 8-bit quantisation and the camera's JPEG compression."""
        if self.s.noise_sigma > 0:
            # Each frame's noise is a window at a random offset into a pool of Gaussian noise a
            # little larger than the frame, one band of which is drawn anew per frame: every
            # frame still carries white Gaussian noise of noise_sigma at every pixel, and no two
            # frames share it pixel for pixel, for a sixteenth of the cost of drawing a frame's
            # worth (the sensor was half of what the synthetic webcam cost the appliance).
            first = self._pool is None
            pool = self._noise_pool()
            dy = dx = 0
            if not first:
                band = -(-pool.shape[0] // _NOISE_BANDS)
                rows = pool[self._noise_band * band:(self._noise_band + 1) * band]
                self._noise_band = (self._noise_band + 1) % _NOISE_BANDS
                cv2.setRNGSeed(int(self.rng.integers(2**31)))
                cv2.randn(rows, 0.0, self.s.noise_sigma)  # type: ignore[call-overload]  # stubs want arrays for scalars
                dy, dx = (int(v) for v in self.rng.integers(0, _NOISE_PAD_PX + 1, size=2))
            noise = pool[dy:dy + img.shape[0], dx:dx + img.shape[1]]
            # One pass: sum, round to nearest and saturate to 0..255, as the 8-bit readout does.
            out = cv2.add(img, noise, dtype=cv2.CV_8U)
        else:
            out = np.clip(img + 0.5, 0, 255).astype(np.uint8)
        if self.s.jpeg_quality is not None:
            ok, data = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(self.s.jpeg_quality)])
            out = np.asarray(cv2.imdecode(data, cv2.IMREAD_GRAYSCALE), dtype=np.uint8)
        return out

    def _noise_pool(self) -> np.ndarray:
        """The sensor's noise pool (float32 grey levels), drawn whole on first use.

        Its top left frame is drawn first, from the generator's next seed, just as a frame's own
        noise was drawn before the pool: a camera's first frame (all a single view renders) is
        the one it always was, and seeded tests and benchmarks see the images they saw."""
        if self._pool is None:
            h, w, pad, sigma = self.height, self.width, _NOISE_PAD_PX, self.s.noise_sigma
            pool = np.empty((h + pad, w + pad), np.float32)
            parts = [np.empty((h, w), np.float32), np.empty((h, pad), np.float32), np.empty((pad, w + pad), np.float32)]
            cv2.setRNGSeed(int(self.rng.integers(2**31)))
            for part in parts:
                cv2.randn(part, 0.0, sigma)  # type: ignore[call-overload]
            pool[:h, :w], pool[:h, w:], pool[h:] = parts
            self._pool = pool
        return self._pool


def box_marker_quads(marker_ids: Sequence[int], T_box_from_marker: Sequence[np.ndarray], marker_size_mm: float,
                     dictionary: str, settings: RenderSettings | None = None) -> list[TexturedQuad]:
    """Printed ArUco markers (with their white margins) placed on a box."""
    s = settings or RenderSettings()
    cells = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).markerSize + 2
    half = marker_size_mm / 2 * (cells + 2 * s.margin_cells) / cells
    return [TexturedQuad(np.asarray(T, dtype=np.float64), half, half, marker_textures(dictionary, i, s.margin_cells))
            for i, T in zip(marker_ids, T_box_from_marker)]


