"""The display characteristic: the log signal onto the monitor's grey scale.

A log amplifier and an automatic window, as a digital fluoroscope's video chain applies
them: the window spans the in-field log signal (its 1st to 99th percentile, widened by the
profile's latitude) about the median of the measuring field, so lungs, soft tissue, bone and contrast all keep gradation; the last
`display_knee` of the scale at each end is reached through a hyperbolic soft knee, so
nothing in the field is clipped to pure black or white. Window and level may be moved by
the radiographer (`View.window_scale`, `View.level_shift`).

Invert has its one owner here: bright = more attenuation unless inverted, every in-field
grey g becoming 1 - g; outside the beam stays black in both polarities (the unit blanks
it). The compositor and the saved images take the result as it is.
"""

from __future__ import annotations

import numpy as np

from ..config.image_chain import ImageChain


def soft_knee(x: np.ndarray, knee: float) -> np.ndarray:
    """Identity on [knee, 1 - knee]; beyond, hyperbolic approaches to 0 and 1 with the same
    value and slope at the joins (1 - y = k^2 / (k + d) a distance d past the knee), slow
    enough that even ten window widths past the end stay a few grey levels short of it."""
    x = np.asarray(x, dtype=np.float32)
    if knee <= 0:
        return np.clip(x, 0.0, 1.0)
    k = np.float32(knee)
    low = k * k / (k + np.maximum(k - x, 0.0))
    high = 1.0 - k * k / (k + np.maximum(x - (1.0 - k), 0.0))
    return np.where(x < k, low, np.where(x > 1.0 - k, high, x)).astype(np.float32)


def unsharp(p: np.ndarray, amount: float, sigma_px: float) -> np.ndarray:
    """Edge enhancement on the log image: p + amount (p - blurred p)."""
    import cv2

    if amount <= 0:
        return p
    return (p + np.float32(amount) * (p - cv2.GaussianBlur(p, (0, 0), sigma_px))).astype(np.float32)


#: The window reads every WINDOW_STEP-th pixel of the field and of the measuring field.
WINDOW_STEP = 3


def auto_window(p: np.ndarray, field: np.ndarray, measuring: np.ndarray, latitude: float,
                min_width: float, indices: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float]:
    """(centre, width) of the window over the in-field log signal `p`.

    The width spans its 1st-99th percentile range times `latitude`; the centre is the median
    over the exposure control's measuring field (the video gain holds the middle of the image
    at mid-grey), moved only as far as needed to keep both percentiles inside the window. A
    sample of every third pixel is enough. `indices`: the flat indices of `field` and
    `measuring` (np.flatnonzero of each), the same pixels without scanning the masks.
    """
    if indices is not None:
        flat = p.ravel()
        values, middle = flat[indices[0][::WINDOW_STEP]], flat[indices[1][::WINDOW_STEP]]
    else:
        values, middle = p[field][::WINDOW_STEP], p[measuring][::WINDOW_STEP]
    return window_of(values, middle, latitude, min_width)


def window_of(values: np.ndarray, middle: np.ndarray, latitude: float, min_width: float) -> tuple[float, float]:
    """`auto_window`'s (centre, width) from its samples: `values` of the field, `middle` of
    the measuring field."""
    if values.size < 16:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(values, (1.0, 99.0)))
    width = max((hi - lo) * latitude, min_width)
    centre = float(np.median(middle)) if middle.size else (lo + hi) / 2.0
    return min(max(centre, hi - width / 2.0), lo + width / 2.0), width


def to_display(p: np.ndarray, edge: np.ndarray, chain: ImageChain, invert: bool,
               centre: float, width: float) -> np.ndarray:
    """(rows, cols) float32 grey in [0, 1] of the log signal `p` through window (centre, width),
    the soft knee and the polarity, faded by `edge` (1 inside the field, 0 outside it, so the
    screen is black beyond the exposed field)."""
    import cv2

    k = float(chain.display_knee)
    # x: the window position (0 its bottom, 1 its top). The soft knee in closed form, a few
    # whole-frame OpenCV passes (a table read per pixel, or np.where's three branches, cost
    # several times more): with c = x clipped to [k, 1 - k] and s = x - c the distance past
    # the knee, grey = c + k s / (k + |s|), which is soft_knee's two hyperbolas and identity.
    x = cv2.addWeighted(p, 1.0 / width, p, 0.0, 0.5 - centre / width)
    if k <= 0:
        grey = np.clip(x, np.float32(0.0), np.float32(1.0))
    else:
        c = np.clip(x, np.float32(k), np.float32(1.0 - k))
        s = cv2.subtract(x, c)
        den = np.abs(s)
        den += np.float32(k)
        grey = cv2.add(c, cv2.divide(s, den, scale=k))
    if invert:
        np.subtract(np.float32(1.0), grey, out=grey)
    return cv2.multiply(grey, edge)
