"""The screen: a Linux framebuffer (/dev/fbN) or a raw file of explicit geometry.

`open_display(target, ...)` gives a `Display` with `show(rgb)`, `read_back()` and `close()`.
The file target is the framebuffer display over a `FakeFramebuffer` whose pixel memory is
that file, so the demo and the tests run the appliance's display code, packer included.

Framebuffer geometry and pixel format come from the driver (FBIOGET_VSCREENINFO and
FBIOGET_FSCREENINFO): width and height in pixels, bits per pixel (16, 24 or 32), the line
stride in bytes, and the offset and length in bits of each colour channel within a pixel.
Packing RGB into those pixels is `pixel_format.PixelFormat`'s job.

No tearing: where the driver offers a virtual screen at least twice the visible height and
can pan along y, each frame is drawn into the hidden half and FBIOPAN_DISPLAY flips to it;
otherwise the frame is packed into a private buffer and copied to the screen in one memcpy.

`FakeFramebuffer` stands in for a /dev/fbN node on machines that have none: a plain file
holding the pixel memory, and the screen information a driver would report. It answers the
same four calls as `LinuxFramebuffer`, so `FramebufferDisplay` runs unchanged on it.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import mmap
import os
from typing import Protocol

import numpy as np

from .pixel_format import PixelFormat

# ioctl numbers from <linux/fb.h>.
FBIOGET_VSCREENINFO = 0x4600
FBIOPUT_VSCREENINFO = 0x4601
FBIOGET_FSCREENINFO = 0x4602
FBIOPAN_DISPLAY = 0x4606

FB_TYPE_PACKED_PIXELS = 0
FB_VISUAL_TRUECOLOR = 2
FB_VISUAL_DIRECTCOLOR = 4
FB_ACTIVATE_NOW = 0


class DisplayError(OSError):
    """A display that cannot be opened or used; the message names the device or file."""


class Bitfield(ctypes.Structure):
    """struct fb_bitfield: where one colour channel sits in a pixel (bits)."""

    _fields_ = [("offset", ctypes.c_uint32), ("length", ctypes.c_uint32), ("msb_right", ctypes.c_uint32)]


class VarScreenInfo(ctypes.Structure):
    """struct fb_var_screeninfo (160 bytes): visible and virtual geometry, pixel format."""

    _fields_ = [
        ("xres", ctypes.c_uint32), ("yres", ctypes.c_uint32),
        ("xres_virtual", ctypes.c_uint32), ("yres_virtual", ctypes.c_uint32),
        ("xoffset", ctypes.c_uint32), ("yoffset", ctypes.c_uint32),
        ("bits_per_pixel", ctypes.c_uint32), ("grayscale", ctypes.c_uint32),
        ("red", Bitfield), ("green", Bitfield), ("blue", Bitfield), ("transp", Bitfield),
        ("nonstd", ctypes.c_uint32), ("activate", ctypes.c_uint32),
        ("height", ctypes.c_uint32), ("width", ctypes.c_uint32), ("accel_flags", ctypes.c_uint32),
        ("pixclock", ctypes.c_uint32), ("left_margin", ctypes.c_uint32), ("right_margin", ctypes.c_uint32),
        ("upper_margin", ctypes.c_uint32), ("lower_margin", ctypes.c_uint32),
        ("hsync_len", ctypes.c_uint32), ("vsync_len", ctypes.c_uint32),
        ("sync", ctypes.c_uint32), ("vmode", ctypes.c_uint32), ("rotate", ctypes.c_uint32),
        ("colorspace", ctypes.c_uint32), ("reserved", ctypes.c_uint32 * 4),
    ]


class FixScreenInfo(ctypes.Structure):
    """struct fb_fix_screeninfo (80 bytes on 64-bit): memory size, line stride, pan steps."""

    _fields_ = [
        ("id", ctypes.c_char * 16), ("smem_start", ctypes.c_ulong), ("smem_len", ctypes.c_uint32),
        ("type", ctypes.c_uint32), ("type_aux", ctypes.c_uint32), ("visual", ctypes.c_uint32),
        ("xpanstep", ctypes.c_uint16), ("ypanstep", ctypes.c_uint16), ("ywrapstep", ctypes.c_uint16),
        ("line_length", ctypes.c_uint32), ("mmio_start", ctypes.c_ulong), ("mmio_len", ctypes.c_uint32),
        ("accel", ctypes.c_uint32), ("capabilities", ctypes.c_uint16), ("reserved", ctypes.c_uint16 * 2),
    ]


class FramebufferDevice(Protocol):
    """The calls `FramebufferDisplay` makes of a framebuffer node."""

    def fileno(self) -> int: ...
    def var_info(self) -> VarScreenInfo: ...
    def fix_info(self) -> FixScreenInfo: ...
    def pan(self, var: VarScreenInfo) -> None: ...
    def put_var(self, var: VarScreenInfo) -> None: ...
    def close(self) -> None: ...


class LinuxFramebuffer:
    """A /dev/fbN node, asked through the fbdev ioctls."""

    def __init__(self, path: str, read_only: bool = False):
        self.path = path
        self.read_only = read_only
        try:
            self._fd = os.open(path, os.O_RDONLY if read_only else os.O_RDWR)
        except FileNotFoundError:
            raise DisplayError(f"{path}: no such framebuffer; check that the graphics driver is loaded "
                               f"(ls /dev/fb*) or set devices.display.target to 'file'") from None
        except PermissionError:
            raise DisplayError(f"{path}: permission denied; the user needs to be in group 'video'") from None

    def fileno(self) -> int:
        return self._fd

    def _ioctl(self, request: int, struct: ctypes.Structure, what: str) -> None:
        try:
            fcntl.ioctl(self._fd, request, struct)
        except OSError as e:
            raise DisplayError(f"{self.path}: {what} failed ({e.strerror}); is this a framebuffer device?") from None

    def var_info(self) -> VarScreenInfo:
        var = VarScreenInfo()
        self._ioctl(FBIOGET_VSCREENINFO, var, "FBIOGET_VSCREENINFO")
        return var

    def fix_info(self) -> FixScreenInfo:
        fix = FixScreenInfo()
        self._ioctl(FBIOGET_FSCREENINFO, fix, "FBIOGET_FSCREENINFO")
        return fix

    def pan(self, var: VarScreenInfo) -> None:
        fcntl.ioctl(self._fd, FBIOPAN_DISPLAY, var)

    def put_var(self, var: VarScreenInfo) -> None:
        fcntl.ioctl(self._fd, FBIOPUT_VSCREENINFO, var)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


class FakeFramebuffer:
    """Stands in for /dev/fbN where the machine has none: pixel memory in a file, driver answers in memory.

    Built with the geometry a driver would report; `pan` and `put_var` check their
    arguments as fbmem.c does (EINVAL when the offset or size does not fit).
    """

    def __init__(self, path: str, width: int, height: int, fmt: PixelFormat, *, stride: int = 0,
                 pages: int = 1, ypanstep: int = 1, smem_len: int = 0, read_only: bool = False):
        self.path = path
        stride = stride or width * fmt.bytes_per_pixel
        self._var = VarScreenInfo(xres=width, yres=height, xres_virtual=width, yres_virtual=height * pages,
                                  bits_per_pixel=fmt.bpp)
        for name, (offset, length) in (("red", fmt.red), ("green", fmt.green), ("blue", fmt.blue), ("transp", fmt.transp)):
            setattr(self._var, name, Bitfield(offset, length, 0))
        self._fix = FixScreenInfo(id=b"fake-fb", smem_len=smem_len or stride * height * pages,
                                  type=FB_TYPE_PACKED_PIXELS, visual=FB_VISUAL_TRUECOLOR,
                                  ypanstep=ypanstep, line_length=stride)
        self.pans = 0
        size = self._fix.smem_len
        try:
            self._fd = os.open(path, os.O_RDONLY if read_only else os.O_RDWR | os.O_CREAT, 0o600)
        except FileNotFoundError:
            raise DisplayError(f"{path}: no screen file; start the appliance (fluorosim run) or check "
                               f"devices.display.path") from None
        except OSError as e:
            raise DisplayError(f"{path}: cannot open the screen file ({e.strerror})") from None
        try:
            actual = os.fstat(self._fd).st_size
            if actual != size and read_only:
                raise DisplayError(f"{path}: holds {actual} bytes but {width}x{height} at {fmt.bpp} bpp with stride "
                                   f"{stride} needs {size}; give the geometry the appliance writes with")
            if not read_only:
                # Reserve the blocks now: a write through the mapping into a sparse file on a full
                # disk would kill the process with SIGBUS instead of raising an error.
                try:
                    if actual != size:
                        os.ftruncate(self._fd, size)
                    os.posix_fallocate(self._fd, 0, size)
                except OSError as e:
                    raise DisplayError(f"{path}: cannot reserve {size} bytes for the screen file ({e.strerror}); "
                                       f"free disk space") from None
        except BaseException:
            self.close()
            raise

    def fileno(self) -> int:
        return self._fd

    def var_info(self) -> VarScreenInfo:
        return VarScreenInfo.from_buffer_copy(self._var)

    def fix_info(self) -> FixScreenInfo:
        return FixScreenInfo.from_buffer_copy(self._fix)

    def pan(self, var: VarScreenInfo) -> None:
        if (self._fix.ypanstep == 0 and var.yoffset != self._var.yoffset) or \
                (self._fix.ypanstep and var.yoffset % self._fix.ypanstep) or \
                var.yoffset + self._var.yres > self._var.yres_virtual:
            raise OSError(errno.EINVAL, "invalid pan")
        self._var.yoffset = var.yoffset
        self.pans += 1

    def put_var(self, var: VarScreenInfo) -> None:
        if var.yres_virtual * self._fix.line_length > self._fix.smem_len:
            raise OSError(errno.EINVAL, "virtual screen exceeds framebuffer memory")
        self._var.yres_virtual = var.yres_virtual

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


class Display:
    """A screen of `width` x `height` pixels at `bpp` bits per pixel."""

    width: int
    height: int
    bpp: int
    stride: int
    pixel_format: PixelFormat

    def show(self, rgb: np.ndarray) -> None:
        """Put a (height, width, 3) uint8 RGB frame on screen, without tearing."""
        raise NotImplementedError

    def read_back(self) -> np.ndarray:
        """What is on screen now, as (height, width, 3) uint8 RGB."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Display:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_frame(self, rgb: np.ndarray) -> None:
        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"frame must be ({self.height}, {self.width}, 3) uint8, got {rgb.shape} {rgb.dtype}")

    def _page(self, memory: np.ndarray, first_row: int) -> np.ndarray:
        """The (height, width * bytes) view of one screen page starting at `first_row` of `memory`."""
        rows = memory[first_row * self.stride:(first_row + self.height) * self.stride].reshape(self.height, self.stride)
        return rows[:, self._x0:self._x0 + self.width * self.pixel_format.bytes_per_pixel]

    _x0 = 0


class FramebufferDisplay(Display):
    """A Linux framebuffer, memory-mapped; double-buffered by panning where the driver allows."""

    def __init__(self, device: FramebufferDevice, read_only: bool = False):
        self.device = device
        self.name = getattr(device, "path", "framebuffer")
        self.read_only = read_only
        var, fix = device.var_info(), device.fix_info()
        self.pixel_format = PixelFormat.from_var(var)
        problem = self.pixel_format.problem()
        if problem is None and (fix.type != FB_TYPE_PACKED_PIXELS or var.grayscale
                                or fix.visual not in (FB_VISUAL_TRUECOLOR, FB_VISUAL_DIRECTCOLOR)):
            problem = f"type {fix.type}, visual {fix.visual}, grayscale {var.grayscale} (a packed true-colour mode is needed)"
        if problem:
            raise DisplayError(f"{self.name}: unsupported pixel format: {problem}; set a 16, 24 or 32 bpp "
                               f"true-colour mode (fbset -depth 32)")
        self.width, self.height, self.bpp = var.xres, var.yres, var.bits_per_pixel
        self.stride = fix.line_length
        self._x0 = var.xoffset * self.pixel_format.bytes_per_pixel
        self._smem_len = fix.smem_len
        self.pages = 1
        if not read_only:
            self.pages = self._enable_double_buffer(var, fix)
        self._page_rows = [p * self.height for p in range(self.pages)]
        self._shown = 0 if self.pages == 1 else (1 if var.yoffset == self.height else 0)
        # Without panning, frames go to the rows the driver shows now (0 unless left panned).
        fits = (var.yoffset + self.height) * self.stride <= fix.smem_len
        self._visible_row = var.yoffset if fits else 0
        try:
            self._mm: mmap.mmap | None = mmap.mmap(device.fileno(), fix.smem_len, mmap.MAP_SHARED,
                                 mmap.PROT_READ if read_only else mmap.PROT_READ | mmap.PROT_WRITE)
        except OSError as e:
            raise DisplayError(f"{self.name}: cannot map {fix.smem_len} bytes of screen memory ({e.strerror})") from None
        self._memory = np.frombuffer(self._mm, dtype=np.uint8)
        row_bytes = self.width * self.pixel_format.bytes_per_pixel
        self._back: np.ndarray | None = None if self.pages > 1 else np.zeros((self.height, row_bytes), np.uint8)

    def _enable_double_buffer(self, var: VarScreenInfo, fix: FixScreenInfo) -> int:
        """2 when a second page is available for panning, else 1."""
        if fix.ypanstep == 0 or self.height % fix.ypanstep:
            return 1
        if var.yres_virtual < 2 * var.yres and fix.smem_len >= 2 * var.yres * fix.line_length:
            wanted = VarScreenInfo.from_buffer_copy(var)
            wanted.yres_virtual = 2 * var.yres
            wanted.activate = FB_ACTIVATE_NOW
            try:
                self.device.put_var(wanted)
                var = self.device.var_info()
            except OSError:
                pass   # the driver keeps its single page: fall back to one copy per frame
        return 2 if var.yres_virtual >= 2 * var.yres and fix.smem_len >= 2 * var.yres * fix.line_length else 1

    @property
    def double_buffered(self) -> bool:
        return self.pages > 1

    def show(self, rgb: np.ndarray) -> None:
        self._check_frame(rgb)
        if self.read_only:
            raise DisplayError(f"{self.name}: opened read-only")
        if self._back is not None:   # one page: pack aside, then one copy to the screen
            self.pixel_format.pack(rgb, self._back)
            self._page(self._memory, self._visible_row)[...] = self._back
            return
        hidden = 1 - self._shown
        self.pixel_format.pack(rgb, self._page(self._memory, self._page_rows[hidden]))
        var = self.device.var_info()
        var.yoffset = self._page_rows[hidden]
        try:
            self.device.pan(var)
        except OSError as e:
            # Panning refused after all: copy the frame to the visible page and stop double-buffering.
            self._page(self._memory, self._page_rows[self._shown])[...] = self._page(self._memory, self._page_rows[hidden])
            self.pages = 1
            self._visible_row = self._page_rows[self._shown]
            self._back = np.zeros((self.height, self.width * self.pixel_format.bytes_per_pixel), np.uint8)
            if e.errno not in (errno.EINVAL, errno.ENOTTY):
                raise DisplayError(f"{self.name}: FBIOPAN_DISPLAY failed ({e.strerror})") from None
            return
        self._shown = hidden

    def read_back(self) -> np.ndarray:
        var = self.device.var_info()
        first_row = var.yoffset if var.yoffset + self.height <= self._smem_len // self.stride else 0
        return self.pixel_format.unpack(np.ascontiguousarray(self._page(self._memory, first_row)))

    def close(self) -> None:
        mm = getattr(self, "_mm", None)
        if mm is not None:
            del self._memory   # the array views the mapping: drop it before unmapping
            mm.close()
            self._mm = None
        self.device.close()


class FileDisplay(FramebufferDisplay):
    """A raw file of `height` rows of `stride` bytes, in the standard format for `bpp` (see
    PixelFormat.standard): the framebuffer display itself over a one-page `FakeFramebuffer`
    that is that file, so the demo and the tests run the appliance's display code."""

    def __init__(self, path: str, width: int, height: int, bpp: int = 32, stride: int = 0, read_only: bool = False):
        if bpp not in (16, 24, 32):
            raise DisplayError(f"{path}: bpp must be 16, 24 or 32, got {bpp}")
        if width <= 0 or height <= 0:
            raise DisplayError(f"{path}: width and height must be positive, got {width}x{height}")
        fmt = PixelFormat.standard(bpp)
        if stride and stride < width * fmt.bytes_per_pixel:
            raise DisplayError(f"{path}: stride {stride} bytes is shorter than a row of {width} pixels at {bpp} bpp")
        node = FakeFramebuffer(path, width, height, fmt, stride=stride, read_only=read_only)
        try:
            super().__init__(node, read_only=read_only)
        except BaseException:
            node.close()
            raise


def open_display(target: str, path: str | None = None, width: int = 0, height: int = 0, bpp: int = 32,
                 *, stride: int = 0, read_only: bool = False) -> Display:
    """Open `target`: a framebuffer node ("/dev/fb0") or "file" (then `path` and the geometry are needed).

    `read_only` opens an existing screen to read it back (a screenshot) without changing it.
    """
    if target == "file":
        if not path:
            raise DisplayError("display target 'file' needs a path (devices.display.path)")
        return FileDisplay(path, width, height, bpp, stride, read_only=read_only)
    if target.startswith("/dev/"):
        device = LinuxFramebuffer(target, read_only=read_only)
        try:
            return FramebufferDisplay(device, read_only=read_only)
        except BaseException:
            device.close()
            raise
    raise DisplayError(f"display target {target!r}: use a framebuffer device such as /dev/fb0, or 'file'")
