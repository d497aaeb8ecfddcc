"""The detector after the cast on the device: a GPU's display frame stays in device memory.

On a CPU device the host's OpenCV and numpy passes are as fast as any kernel and the image is
in host memory anyway. On a GPU each of those passes (the focal blur, the noise's upload and
download, the detector's spread and glare, the recursive filter, the log, the unsharp mask,
the window and the display) costs more than the cast itself: at 1024 x 1024 they were 15-18 ms
of a 22 ms frame. Here they run as kernels of detector_chain.cl, and what comes back to the
host is the frame (and the signal the display was given) and the few samples the exposure
control and the window read.

Every blur and resize is a tap table applied along rows and then columns: OpenCV's Gaussian
taps with its reflect-101 border (`gaussian_taps`), INTER_AREA's weights to a coarser grid and
INTER_LINEAR's back (`area_taps`, `linear_taps`), so the device computes what the host's
cv2.GaussianBlur and cv2.resize do, to float32 rounding.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

SOURCE = Path(__file__).with_name("detector_chain.cl")
KERNELS = ("resample_rows", "resample_cols", "multiply", "glare_gain", "gather", "recursive", "neg_log",
           "unsharp_mix", "display")


def _reflect101(p: np.ndarray, n: int) -> np.ndarray:
    """OpenCV's BORDER_REFLECT_101 (gfedcb|abcdefgh|gfedcba) for indices any distance outside [0, n)."""
    if n == 1:
        return np.zeros_like(p)
    period = 2 * (n - 1)
    p = np.abs(p) % period
    return np.where(p >= n, period - p, p)


def gaussian_taps(n: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(idx, w), each (n, taps): cv2.GaussianBlur(x, (0, 0), sigma) along an axis of n pixels
    of float32 (its kernel size round(8 sigma + 1) | 1, its taps, its default border)."""
    import cv2

    ksize = int(round(sigma * 4 * 2 + 1)) | 1
    w = cv2.getGaussianKernel(ksize, sigma, cv2.CV_32F).ravel().astype(np.float32)
    r = ksize // 2
    idx = _reflect101(np.arange(n)[:, None] + np.arange(-r, r + 1)[None, :], n)
    return idx.astype(np.int32), np.broadcast_to(w, idx.shape).astype(np.float32)


def area_taps(n_src: int, n_dst: int) -> tuple[np.ndarray, np.ndarray]:
    """(idx, w) of cv2.resize's INTER_AREA from n_src to fewer n_dst pixels: each coarse
    pixel the mean of the fine ones it covers, partial ones by their covered fraction
    (OpenCV's computeResizeAreaTab)."""
    scale = n_src / n_dst
    rows: list[list[tuple[int, float]]] = []
    for dx in range(n_dst):
        fsx1 = dx * scale
        fsx2 = fsx1 + scale
        cell = min(scale, n_src - fsx1)
        sx1, sx2 = math.ceil(fsx1), math.floor(fsx2)
        sx2 = min(sx2, n_src - 1)
        sx1 = min(sx1, sx2)
        taps = []
        if sx1 - fsx1 > 1e-3:
            taps.append((sx1 - 1, (sx1 - fsx1) / cell))
        taps += [(sx, 1.0 / cell) for sx in range(sx1, sx2)]
        if fsx2 - sx2 > 1e-3:
            taps.append((sx2, min(min(fsx2 - sx2, 1.0), cell) / cell))
        rows.append(taps)
    return _table(rows)


def linear_taps(n_src: int, n_dst: int) -> tuple[np.ndarray, np.ndarray]:
    """(idx, w) of cv2.resize's INTER_LINEAR from n_src to n_dst pixels: pixel centres mapped
    (dst + 0.5) n_src / n_dst - 0.5, the two neighbours weighted, clamped at the ends."""
    scale = n_src / n_dst
    rows = []
    for dx in range(n_dst):
        fx = (dx + 0.5) * scale - 0.5
        sx = math.floor(fx)
        fx -= sx
        if sx < 0:
            sx, fx = 0, 0.0
        if sx >= n_src - 1:
            sx, fx = n_src - 1, 0.0
        rows.append([(sx, 1.0 - fx), (min(sx + 1, n_src - 1), fx)])
    return _table(rows)


def _table(rows: list[list[tuple[int, float]]]) -> tuple[np.ndarray, np.ndarray]:
    taps = max(len(r) for r in rows)
    idx = np.zeros((len(rows), taps), np.int32)
    w = np.zeros((len(rows), taps), np.float32)
    for i, r in enumerate(rows):
        for k, (s, weight) in enumerate(r):
            idx[i, k], w[i, k] = s, weight
        if len(r) < taps:
            idx[i, len(r):] = r[-1][0]          # padding taps read a real pixel with weight 0
    return idx, w


def resample_host(x: np.ndarray, rows: tuple[np.ndarray, np.ndarray], cols: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The tables applied in numpy (float64): what the kernels compute, for checking them."""
    (ri, rw), (ci, cw) = rows, cols
    y = (np.asarray(x, np.float64)[:, ci] * cw).sum(axis=2)     # along each row: columns resampled
    return (y[ri, :] * rw[:, :, None]).sum(axis=1)               # down the columns


def _kept(cache: dict, key, owner, make, limit: int):
    """cache[key]'s value, made by `make()` where missing or made for another `owner` (an array
    freed and its id taken by a new one); the cache emptied once it holds `limit` entries."""
    got = cache.get(key)
    if got is None or got[0] is not owner:
        if len(cache) >= limit:
            cache.clear()
        got = cache[key] = (owner, make())
    return got[1]


class DeviceChain:
    """The kernels of detector_chain.cl on one ClDevice, with the tap tables and the device
    copies of the per-field arrays (field, normalisation, gain, edge, sample indices) they
    read, made once per size or array. Called under the device's lock."""

    def __init__(self, dev):
        self.dev = dev
        cl = dev.cl
        self.program = cl.Program(dev.ctx, SOURCE.read_text()).build()
        self._k = {name: cl.Kernel(self.program, name) for name in KERNELS}
        self._tables: dict = {}
        self._held: dict = {}
        self._strided: dict = {}

    # -- device copies -------------------------------------------------------------------
    def held(self, host: np.ndarray, dtype=np.float32):
        """A read-only device copy of `host` as `dtype` (an array kept for a field: the same
        object, the same copy)."""
        return _kept(self._held, id(host), host, lambda: self.dev.upload(np.ascontiguousarray(host, dtype=dtype)), 64)

    def every(self, index: np.ndarray, step: int) -> np.ndarray:
        """index[::step], the same array for the same `index` (so its device copy is made once)."""
        return _kept(self._strided, (id(index), step), index, lambda: np.ascontiguousarray(index[::step]), 16)

    def new(self, n: int):
        return self.dev.scratch(4 * n)

    def upload(self, image: np.ndarray):
        return self.dev.upload(np.ascontiguousarray(image, dtype=np.float32), writable=True)

    def download(self, buf, shape) -> np.ndarray:
        return self.dev.download(buf, np.empty(shape, np.float32))

    # -- resampling ------------------------------------------------------------------------
    def _table(self, key: tuple, make):
        """(idx, w, taps, outputs) of a tap table on the device. The focal blur's sigma follows
        the patient's depth, a new one at nearly every pose: the cache is bounded."""
        def upload():
            idx, w = make()
            return (self.dev.upload(np.ascontiguousarray(idx, np.int32)),
                    self.dev.upload(np.ascontiguousarray(w, np.float32)), idx.shape[1], idx.shape[0])
        return _kept(self._tables, key, None, upload, 32)

    def resample(self, buf, shape: tuple[int, int], rows_key: tuple, rows_make, cols_key: tuple, cols_make):
        """`buf` (rows, cols) resampled by a table along each row, then one down the columns:
        (new buffer, its shape)."""
        rows, cols = shape
        ci, cw, ctaps, dst_cols = self._table(cols_key, cols_make)
        ri, rw, rtaps, dst_rows = self._table(rows_key, rows_make)
        q = self.dev.queue
        mid = self.new(rows * dst_cols)
        self._k["resample_rows"](q, (dst_cols, rows), None, buf, mid, ci, cw, np.int32(ctaps), np.int32(cols),
                                 np.int32(dst_cols))
        out = self.new(dst_rows * dst_cols)
        self._k["resample_cols"](q, (dst_cols, dst_rows), None, mid, out, ri, rw, np.int32(rtaps), np.int32(dst_cols))
        return out, (dst_rows, dst_cols)

    def blur(self, buf, shape: tuple[int, int], sigma: float):
        """cv2.GaussianBlur(image, (0, 0), sigma) on the device."""
        rows, cols = shape
        s = float(sigma)
        out, _ = self.resample(buf, shape, ("gauss", rows, s), lambda: gaussian_taps(rows, s),
                               ("gauss", cols, s), lambda: gaussian_taps(cols, s))
        return out

    def resize(self, buf, shape: tuple[int, int], to: tuple[int, int], how: str):
        """cv2.resize(image, (to cols, to rows), interpolation=INTER_AREA ("area") or
        INTER_LINEAR ("linear")) on the device."""
        taps = area_taps if how == "area" else linear_taps
        (rows, cols), (to_rows, to_cols) = shape, to
        out, _ = self.resample(buf, shape, (how, rows, to_rows), lambda: taps(rows, to_rows),
                               (how, cols, to_cols), lambda: taps(cols, to_cols))
        return out

    def spread(self, buf, shape: tuple[int, int], detector, mask: np.ndarray, zoom: int):
        """Detector.spread on the device: the point-spread normalised by the blurred field, the
        veiling glare's halo on its coarse grid, the vignetting."""
        from .detector import BLUR_MIN_SIGMA_PX

        n = shape[0] * shape[1]
        sigma, field, inv_weight, gain = detector.field_weights(mask, zoom)
        self.multiply(buf, n, field)
        if sigma > BLUR_MIN_SIGMA_PX:
            buf = self.blur(buf, shape, sigma)
            self.multiply(buf, n, inv_weight)
        glare = detector.glare(zoom, shape)
        if glare is None:
            self.multiply(buf, n, gain)
            return buf
        g, small_shape, small_sigma = glare
        small = self.blur(self.resize(buf, shape, small_shape, "area"), small_shape, small_sigma)
        self.glare_gain(buf, self.resize(small, small_shape, shape, "linear"), n, gain, g)
        return buf

    # -- pixelwise -------------------------------------------------------------------------
    def multiply(self, buf, n: int, by: np.ndarray) -> None:
        self._k["multiply"](self.dev.queue, (n,), None, buf, self.held(by))

    def glare_gain(self, buf, halo, n: int, gain: np.ndarray, g: float) -> None:
        self._k["glare_gain"](self.dev.queue, (n,), None, buf, halo, self.held(gain), np.float32(g))

    def gather(self, buf, index: np.ndarray) -> np.ndarray:
        """buf's values at the flat indices `index` (an array kept for a field), to the host."""
        out = np.empty(len(index), np.float32)
        if len(index):
            dst = self.new(len(index))
            self._k["gather"](self.dev.queue, (len(index),), None, buf, self.held(index, np.int32), dst)
            self.dev.download(dst, out)
        return out

    def recursive(self, state, x, n: int, weight: float) -> None:
        self._k["recursive"](self.dev.queue, (n,), None, state, x, np.float32(weight))

    def copy(self, buf, n: int):
        out = self.new(n)
        self.dev.cl.enqueue_copy(self.dev.queue, out, buf, byte_count=4 * n)
        return out

    def neg_log(self, buf, n: int, floor: float):
        out = self.new(n)
        self._k["neg_log"](self.dev.queue, (n,), None, buf, out, np.float32(floor))
        return out

    def unsharp(self, buf, shape: tuple[int, int], amount: float, sigma_px: float) -> None:
        """display_lut.unsharp in place: p + amount (p - blurred p)."""
        if amount <= 0:
            return
        blurred = self.blur(buf, shape, sigma_px)
        self._k["unsharp_mix"](self.dev.queue, (shape[0] * shape[1],), None, buf, blurred, np.float32(amount))

    def display(self, p, shape: tuple[int, int], edge: np.ndarray, knee: float, invert: bool, centre: float,
                width: float) -> np.ndarray:
        """display_lut.to_display on the device: the frame's grey, to the host."""
        n = shape[0] * shape[1]
        out = self.new(n)
        self._k["display"](self.dev.queue, (n,), None, p, self.held(edge), out, np.float32(1.0 / width),
                           np.float32(0.5 - centre / width), np.float32(knee), np.int32(bool(invert)))
        return self.download(out, shape)
