"""Packed true-colour pixels as a framebuffer driver describes them, and packing RGB into them.

Pixels are stored in the CPU's byte order (little-endian on every machine this runs on).
Bits of a pixel that belong to no colour channel (the X of XRGB8888, the alpha of ARGB) are
written as ones, so a driver that reads them as alpha sees an opaque screen.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from .framebuffer import VarScreenInfo


@dataclass(frozen=True)
class PixelFormat:
    """A packed true-colour pixel: bits per pixel and (offset, length) in bits of each channel."""

    bpp: int
    red: tuple[int, int]
    green: tuple[int, int]
    blue: tuple[int, int]
    transp: tuple[int, int] = (0, 0)

    @classmethod
    def standard(cls, bpp: int) -> PixelFormat:
        """The usual Linux layout: RGB565, BGR byte order at 24 bpp, XRGB8888 at 32 bpp."""
        if bpp == 16:
            return cls(16, (11, 5), (5, 6), (0, 5))
        if bpp == 24:
            return cls(24, (16, 8), (8, 8), (0, 8))
        if bpp == 32:
            return cls(32, (16, 8), (8, 8), (0, 8))
        raise ValueError(f"bpp must be 16, 24 or 32, got {bpp}")

    @classmethod
    def from_var(cls, var: VarScreenInfo) -> PixelFormat:
        return cls(var.bits_per_pixel, (var.red.offset, var.red.length), (var.green.offset, var.green.length),
                   (var.blue.offset, var.blue.length), (var.transp.offset, var.transp.length))

    @property
    def bytes_per_pixel(self) -> int:
        return self.bpp // 8

    def problem(self) -> str | None:
        """Why this format cannot be drawn, or None."""
        if self.bpp not in (16, 24, 32):
            return f"{self.bpp} bits per pixel (only 16, 24 and 32 are supported)"
        for name, (offset, length) in (("red", self.red), ("green", self.green), ("blue", self.blue)):
            if not 1 <= length <= 16 or offset + length > self.bpp:
                return f"{name} channel at bit {offset}, {length} bits, does not fit a {self.bpp}-bit pixel"
        return None

    def _channel_mask(self, offset: int, length: int) -> int:
        return ((1 << length) - 1) << offset if length else 0

    @property
    def padding_bits(self) -> int:
        """Bits that belong to no colour channel; written as ones."""
        used = 0
        for offset, length in (self.red, self.green, self.blue):
            used |= self._channel_mask(offset, length)
        return ((1 << self.bpp) - 1) & ~used

    def _byte_order(self) -> str | None:
        """'BGR' or 'RGB' when each channel is one whole byte with blue or red first in memory."""
        if any(length != 8 or offset % 8 for offset, length in (self.red, self.green, self.blue)):
            return None
        if (self.red[0], self.green[0], self.blue[0]) == (16, 8, 0):
            return "BGR"
        if (self.red[0], self.green[0], self.blue[0]) == (0, 8, 16):
            return "RGB"
        return None

    def pack(self, rgb: np.ndarray, out: np.ndarray) -> None:
        """Write (h, w, 3) uint8 RGB into `out`, an (h, w * bytes_per_pixel) uint8 array (may be a strided view)."""
        h, w = rgb.shape[:2]
        order = self._byte_order()
        packed = None
        if order is not None and self.bpp == 32 and self.padding_bits == 0xFF000000:
            code = cv2.COLOR_RGB2BGRA if order == "BGR" else cv2.COLOR_RGB2RGBA
            if out.flags.c_contiguous:
                # Converted straight into `out`: a 32 bpp screen is 4-5 MB, and a converted copy
                # costs its allocation and one more pass over it on every frame.
                cv2.cvtColor(rgb, code, dst=out.reshape(h, w, 4))
                return
            packed = cv2.cvtColor(rgb, code)
        elif order is not None and self.bpp == 24:
            packed = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if order == "BGR" else rgb
        elif self.bpp == 16 and (self.red, self.green, self.blue) == ((11, 5), (5, 6), (0, 5)):
            packed = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR565)   # OpenCV's "BGR565" keeps red in the top bits
        elif self.bpp == 16 and (self.red, self.green, self.blue) == ((0, 5), (5, 6), (11, 5)):
            packed = cv2.cvtColor(rgb, cv2.COLOR_BGR2BGR565)
        if packed is not None:
            out[...] = packed.reshape(h, w * self.bytes_per_pixel)
            return
        value = np.full((h, w), self.padding_bits, dtype=np.uint32)
        for c, (offset, length) in enumerate((self.red, self.green, self.blue)):
            channel: np.ndarray = rgb[:, :, c].astype(np.uint32)
            if length <= 8:
                channel >>= 8 - length
            else:   # widen by repeating the high bits, so 255 becomes all ones
                channel = (channel << (length - 8)) | (channel >> (16 - length))
            value |= channel << offset
        as_bytes = value.astype("<u4").view(np.uint8).reshape(h, w, 4)[:, :, :self.bytes_per_pixel]
        out[...] = as_bytes.reshape(h, w * self.bytes_per_pixel)

    def unpack(self, packed: np.ndarray) -> np.ndarray:
        """(h, w * bytes_per_pixel) uint8 pixels -> (h, w, 3) uint8 RGB, low bits filled by repetition."""
        h = packed.shape[0]
        bpp_bytes = self.bytes_per_pixel
        w = packed.shape[1] // bpp_bytes
        order = self._byte_order()
        if order is not None:   # whole-byte channels: a channel shuffle, no bit arithmetic
            pixels = np.ascontiguousarray(packed).reshape(h, w, bpp_bytes)
            if bpp_bytes == 4:
                return cv2.cvtColor(pixels, cv2.COLOR_BGRA2RGB if order == "BGR" else cv2.COLOR_RGBA2RGB)
            return cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB) if order == "BGR" else pixels.copy()
        raw = np.zeros((h, w, 4), dtype=np.uint8)
        raw[:, :, :bpp_bytes] = packed.reshape(h, w, bpp_bytes)
        value = raw.view("<u4").reshape(h, w).astype(np.uint32)
        rgb = np.empty((h, w, 3), dtype=np.uint8)
        for c, (offset, length) in enumerate((self.red, self.green, self.blue)):
            channel = (value >> offset) & ((1 << length) - 1)
            if length < 8:
                channel = (channel << (8 - length)) | (channel >> max(2 * length - 8, 0))
                channel &= 0xFF
            elif length > 8:
                channel >>= length - 8
            rgb[:, :, c] = channel
        return rgb
