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

import functools

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


def auto_window(p: np.ndarray, field: np.ndarray, measuring: np.ndarray, latitude: float,
                min_width: float) -> tuple[float, float]:
    """(centre, width) of the window over the in-field log signal `p`.

    The width spans its 1st-99th percentile range times `latitude`; the centre is the median
    over the exposure control's measuring field (the video gain holds the middle of the image
    at mid-grey), moved only as far as needed to keep both percentiles inside the window. A
    sample of every third pixel is enough.
    """
    values = p[field][::3]
    if values.size < 16:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(values, (1.0, 99.0)))
    width = max((hi - lo) * latitude, min_width)
    middle = p[measuring][::3]
    centre = float(np.median(middle)) if middle.size else (lo + hi) / 2.0
    return min(max(centre, hi - width / 2.0), lo + width / 2.0), width


def to_display(p: np.ndarray, field: np.ndarray, edge: np.ndarray, chain: ImageChain, invert: bool,
               centre: float, width: float) -> np.ndarray:
    """(rows, cols) float32 grey in [0, 1] of the log signal `p` through window (centre, width),
    the soft knee and the polarity, faded by `edge` (1 inside the field, 0 outside)."""
    # Through a table of the knee, polarity included, 1/2048 of the window per entry, read by
    # index with linear interpolation between entries (np.interp's search per pixel cost more
    # than the rest of the display chain).
    table = _knee_table(chain.display_knee, invert)
    x = p - np.float32(centre - (0.5 - KNEE_TABLE_LOW) * width)
    x *= np.float32(KNEE_TABLE_STEPS / width)
    np.clip(x, 0, len(table) - 1.001, out=x)
    index = x.astype(np.int32)
    x -= index
    grey = table[index]
    grey += x * (table[index + 1] - grey)
    grey *= edge
    grey[~field] = 0.0
    return grey


#: The knee table spans window positions KNEE_TABLE_LOW .. KNEE_TABLE_HIGH (0 = the window's
#: bottom, 1 = its top) in steps of 1 / KNEE_TABLE_STEPS; beyond, the soft knee is within a
#: few grey levels of its end anyway.
KNEE_TABLE_LOW, KNEE_TABLE_HIGH, KNEE_TABLE_STEPS = -4.0, 5.0, 2048


@functools.lru_cache(maxsize=8)
def _knee_table(knee: float, invert: bool) -> np.ndarray:
    n = int(round((KNEE_TABLE_HIGH - KNEE_TABLE_LOW) * KNEE_TABLE_STEPS)) + 1
    grey = soft_knee(np.linspace(KNEE_TABLE_LOW, KNEE_TABLE_HIGH, n, dtype=np.float64), knee)
    table = ((1.0 - grey) if invert else grey).astype(np.float32)
    table.setflags(write=False)      # shared by every frame
    return table
