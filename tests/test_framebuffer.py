"""The framebuffer driver: struct layout against the kernel header, pixel bytes checked one by one."""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from drivers.framebuffer import (
    DisplayError,
    FakeFramebuffer,
    FileDisplay,
    FixScreenInfo,
    FramebufferDisplay,
    VarScreenInfo,
    open_display,
)
from drivers.pixel_format import PixelFormat

RNG = np.random.default_rng(7)


def random_frame(h, w):
    frame = RNG.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    frame[0, 0] = (255, 255, 255)   # extremes: all bits of every channel set, and none
    frame[0, 1] = (0, 0, 0)
    frame[0, 2] = (255, 0, 0)
    return frame


# ---------------------------------------------------------------- kernel ABI

C_PROGRAM = r"""
#include <stdio.h>
#include <stddef.h>
#include <sys/ioctl.h>
#include <linux/fb.h>
int main(void) {
    printf("%zu %zu %zu %zu %zu %zu %zu %zu %zu %zu\n",
        sizeof(struct fb_var_screeninfo), sizeof(struct fb_fix_screeninfo),
        offsetof(struct fb_var_screeninfo, yoffset), offsetof(struct fb_var_screeninfo, bits_per_pixel),
        offsetof(struct fb_var_screeninfo, red), offsetof(struct fb_var_screeninfo, transp),
        offsetof(struct fb_var_screeninfo, colorspace), offsetof(struct fb_fix_screeninfo, smem_len),
        offsetof(struct fb_fix_screeninfo, ypanstep), offsetof(struct fb_fix_screeninfo, line_length));
    printf("%lu %lu %lu %lu\n", (unsigned long)FBIOGET_VSCREENINFO, (unsigned long)FBIOPUT_VSCREENINFO,
        (unsigned long)FBIOGET_FSCREENINFO, (unsigned long)FBIOPAN_DISPLAY);
    return 0;
}
"""


def test_screeninfo_structs_match_linux_fb_h(tmp_path):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None or not os.path.exists("/usr/include/linux/fb.h"):
        pytest.skip("no C compiler or no linux/fb.h (Debian: gcc, linux-libc-dev) to read the kernel's layout from")
    src = tmp_path / "fb.c"
    src.write_text(C_PROGRAM)
    subprocess.run([cc, str(src), "-o", str(tmp_path / "fb")], check=True, capture_output=True)
    sizes, ioctls = subprocess.run([str(tmp_path / "fb")], check=True, capture_output=True, text=True).stdout.splitlines()
    expected = [int(x) for x in sizes.split()]
    ours = [ctypes.sizeof(VarScreenInfo), ctypes.sizeof(FixScreenInfo),
            VarScreenInfo.yoffset.offset, VarScreenInfo.bits_per_pixel.offset, VarScreenInfo.red.offset,
            VarScreenInfo.transp.offset, VarScreenInfo.colorspace.offset, FixScreenInfo.smem_len.offset,
            FixScreenInfo.ypanstep.offset, FixScreenInfo.line_length.offset]
    assert ours == expected
    from drivers import framebuffer as fb
    assert [fb.FBIOGET_VSCREENINFO, fb.FBIOPUT_VSCREENINFO, fb.FBIOGET_FSCREENINFO, fb.FBIOPAN_DISPLAY] == \
        [int(x) for x in ioctls.split()]


# ---------------------------------------------------------------- file target, standard formats

def expected_pixel_bytes(bpp, r, g, b):
    """The bytes of one pixel in the standard Linux layouts, worked out by hand."""
    if bpp == 16:   # RGB565, little-endian: rrrrrggg gggbbbbb
        v = ((r >> 3) << 11) | ((g >> 2) << 5) | (b >> 3)
        return bytes([v & 0xFF, v >> 8])
    if bpp == 24:   # blue first in memory
        return bytes([b, g, r])
    return bytes([b, g, r, 0xFF])   # XRGB8888 with the X byte set


@pytest.mark.parametrize("bpp", [16, 24, 32])
def test_file_display_writes_each_pixel_in_the_standard_format(tmp_path, bpp):
    w, h = 13, 6
    row = w * bpp // 8
    stride = row + 12                      # padding the driver leaves at each line end
    path = tmp_path / "screen.raw"
    frame = random_frame(h, w)
    with FileDisplay(str(path), w, h, bpp, stride=stride) as display:
        display.show(frame)
    data = path.read_bytes()
    assert len(data) == stride * h
    n = bpp // 8
    for y in range(h):
        for x in range(w):
            r, g, b = (int(c) for c in frame[y, x])
            got = data[y * stride + x * n: y * stride + (x + 1) * n]
            assert got == expected_pixel_bytes(bpp, r, g, b), (y, x)
        assert data[y * stride + row:(y + 1) * stride] == bytes(12), "line padding must stay untouched"


@pytest.mark.parametrize("bpp", [16, 24, 32])
def test_file_display_read_back_from_a_second_reader(tmp_path, bpp):
    w, h = 9, 4
    path = str(tmp_path / "screen.raw")
    frame = random_frame(h, w)
    writer = open_display("file", path, w, h, bpp)
    writer.show(frame)
    reader = open_display("file", path, w, h, bpp, read_only=True)
    back = reader.read_back()
    if bpp == 16:   # 5 and 6 bit channels come back with their high bits repeated into the low ones
        r5, g6, b5 = frame[..., 0].astype(int) >> 3, frame[..., 1].astype(int) >> 2, frame[..., 2].astype(int) >> 3
        expected = np.stack([(r5 << 3) | (r5 >> 2), (g6 << 2) | (g6 >> 4), (b5 << 3) | (b5 >> 2)], axis=-1)
        assert back[0, 0].tolist() == [255, 255, 255]
    else:
        expected = frame
    np.testing.assert_array_equal(back, expected)
    # The writer's next frame is visible to the reader, which has its own mapping.
    writer.show(255 - frame)
    assert reader.read_back()[0, 1].tolist() == [255, 255, 255]
    with pytest.raises(DisplayError, match="read-only"):
        reader.show(frame)
    writer.close()
    reader.close()


def test_file_display_problems_name_the_file(tmp_path):
    missing = str(tmp_path / "none.raw")
    with pytest.raises(DisplayError, match="none.raw: no screen file"):
        open_display("file", missing, 10, 10, 32, read_only=True)
    path = tmp_path / "small.raw"
    path.write_bytes(bytes(100))
    with pytest.raises(DisplayError, match="small.raw: holds 100 bytes but 10x10 at 32 bpp"):
        open_display("file", str(path), 10, 10, 32, read_only=True)
    with pytest.raises(DisplayError, match="bpp must be 16, 24 or 32"):
        open_display("file", str(path), 10, 10, 8)
    with pytest.raises(DisplayError, match="needs a path"):
        open_display("file", None, 10, 10)
    with pytest.raises(DisplayError, match="use a framebuffer device"):
        open_display("hdmi", None)
    with pytest.raises(DisplayError, match="/dev/fb-none: no such framebuffer"):
        open_display("/dev/fb-none")
    with FileDisplay(str(path), 10, 10, 32) as display:   # a writer resizes a stale file to its geometry
        with pytest.raises(ValueError, match=r"\(10, 10, 3\) uint8"):
            display.show(np.zeros((10, 11, 3), np.uint8))
    assert path.stat().st_size == 400


# ---------------------------------------------------------------- framebuffer over the fake node

def pixel_value(fmt: PixelFormat, r, g, b):
    """One pixel as an integer, from the driver's bitfields: top bits of each channel; unused bits ones."""
    v, used = 0, 0
    for c, (offset, length) in zip((r, g, b), (fmt.red, fmt.green, fmt.blue)):
        v |= (c >> (8 - length)) << offset
        used |= ((1 << length) - 1) << offset
    return v | (((1 << fmt.bpp) - 1) & ~used)


FORMATS = {
    "RGB565": PixelFormat(16, (11, 5), (5, 6), (0, 5)),
    "BGR565": PixelFormat(16, (0, 5), (5, 6), (11, 5)),
    "XRGB1555": PixelFormat(16, (10, 5), (5, 5), (0, 5)),
    "RGB888": PixelFormat(24, (16, 8), (8, 8), (0, 8)),
    "BGR888": PixelFormat(24, (0, 8), (8, 8), (16, 8)),
    "XRGB8888": PixelFormat(32, (16, 8), (8, 8), (0, 8)),
    "ARGB8888": PixelFormat(32, (16, 8), (8, 8), (0, 8), (24, 8)),
    "ABGR8888": PixelFormat(32, (0, 8), (8, 8), (16, 8), (24, 8)),
    "RGBX8888": PixelFormat(32, (24, 8), (16, 8), (8, 8)),
}


@pytest.mark.parametrize("name", list(FORMATS))
def test_framebuffer_packs_the_format_the_driver_reports(tmp_path, name):
    fmt = FORMATS[name]
    w, h, n = 11, 5, fmt.bytes_per_pixel
    stride = w * n + 8
    node = FakeFramebuffer(str(tmp_path / "fb"), w, h, fmt, stride=stride, ypanstep=0)
    display = FramebufferDisplay(node)
    assert (display.width, display.height, display.bpp, display.stride) == (w, h, fmt.bpp, stride)
    assert not display.double_buffered
    frame = random_frame(h, w)
    display.show(frame)
    data = (tmp_path / "fb").read_bytes()
    for y in range(h):
        for x in range(w):
            want = pixel_value(fmt, *(int(c) for c in frame[y, x])).to_bytes(n, "little")
            assert data[y * stride + x * n:y * stride + (x + 1) * n] == want, (name, y, x)
        assert data[y * stride + w * n:(y + 1) * stride] == bytes(8)
    back = display.read_back()
    keep = [0xFF & ~((1 << (8 - length)) - 1) for length in (fmt.red[1], fmt.green[1], fmt.blue[1])]
    np.testing.assert_array_equal(back & np.array(keep, np.uint8), frame & np.array(keep, np.uint8))
    display.close()


def test_double_buffering_draws_the_hidden_page_and_pans_to_it(tmp_path):
    fmt = FORMATS["XRGB8888"]
    w, h = 8, 6
    node = FakeFramebuffer(str(tmp_path / "fb"), w, h, fmt, pages=2, ypanstep=1)
    display = FramebufferDisplay(node)
    assert display.double_buffered
    page = w * 4 * h
    a, b = random_frame(h, w), random_frame(h, w)
    display.show(a)
    assert node.var_info().yoffset == h and node.pans == 1
    data = (tmp_path / "fb").read_bytes()
    assert data[:page] == bytes(page), "the visible page was not written while it was shown"
    assert data[page:page + 4] == bytes([a[0, 0, 2], a[0, 0, 1], a[0, 0, 0], 255])
    np.testing.assert_array_equal(display.read_back(), a)
    display.show(b)
    assert node.var_info().yoffset == 0 and node.pans == 2
    np.testing.assert_array_equal(display.read_back(), b)
    data = (tmp_path / "fb").read_bytes()
    assert data[page:page + 4] == bytes([a[0, 0, 2], a[0, 0, 1], a[0, 0, 0], 255]), "the page now hidden keeps frame a"
    display.close()


def test_double_buffering_asks_for_a_taller_virtual_screen_when_memory_allows(tmp_path):
    fmt = FORMATS["RGB565"]
    node = FakeFramebuffer(str(tmp_path / "fb"), 8, 4, fmt, pages=1, ypanstep=2, smem_len=8 * 2 * 4 * 2)
    display = FramebufferDisplay(node)
    assert display.double_buffered and node.var_info().yres_virtual == 8
    display.show(random_frame(4, 8))
    assert node.var_info().yoffset == 4
    display.close()


def test_without_panning_one_copy_per_frame_and_no_pan(tmp_path):
    fmt = FORMATS["RGB888"]
    node = FakeFramebuffer(str(tmp_path / "fb"), 8, 4, fmt, pages=2, ypanstep=0)
    display = FramebufferDisplay(node)
    assert not display.double_buffered
    frame = random_frame(4, 8)
    display.show(frame)
    assert node.pans == 0 and node.var_info().yoffset == 0
    np.testing.assert_array_equal(display.read_back(), frame)
    display.close()


def test_a_driver_that_stops_panning_keeps_getting_frames_on_the_visible_page(tmp_path):
    fmt = FORMATS["XRGB8888"]
    node = FakeFramebuffer(str(tmp_path / "fb"), 8, 4, fmt, pages=2, ypanstep=1)
    display = FramebufferDisplay(node)
    a, b, c = random_frame(4, 8), random_frame(4, 8), random_frame(4, 8)
    display.show(a)
    assert node.var_info().yoffset == 4
    node._fix.ypanstep = 0            # the driver now refuses to move the visible page
    display.show(b)
    assert not display.double_buffered and node.var_info().yoffset == 4
    np.testing.assert_array_equal(display.read_back(), b)
    display.show(c)
    np.testing.assert_array_equal(display.read_back(), c)
    display.close()


def test_single_buffering_draws_where_the_driver_was_left_panned(tmp_path):
    fmt = FORMATS["RGB565"]
    node = FakeFramebuffer(str(tmp_path / "fb"), 8, 4, fmt, pages=2, ypanstep=1)
    node._var.yoffset = 4             # a previous run left the second page on screen
    node._fix.ypanstep = 0
    display = FramebufferDisplay(node)
    assert not display.double_buffered
    frame = np.full((4, 8, 3), 255, np.uint8)
    display.show(frame)
    data = (tmp_path / "fb").read_bytes()
    assert data[:8 * 2 * 4] == bytes(8 * 2 * 4) and data[8 * 2 * 4:] == b"\xff" * (8 * 2 * 4)
    display.close()


def test_unsupported_modes_are_refused_with_the_device_named(tmp_path):
    node = FakeFramebuffer(str(tmp_path / "fb"), 8, 4, PixelFormat(8, (0, 8), (0, 8), (0, 8)))
    with pytest.raises(DisplayError, match=r"fb: unsupported pixel format: 8 bits per pixel.*fbset -depth 32"):
        FramebufferDisplay(node)


def test_real_framebuffer_node_when_present():
    path = "/dev/fb0"
    if not os.path.exists(path):
        pytest.skip("this machine has no /dev/fb0 (no graphics framebuffer); the fake node covers the driver")
    try:
        display = open_display(path, read_only=True)
    except DisplayError as e:
        pytest.skip(f"/dev/fb0 present but not usable here: {e}")
    try:
        assert display.read_back().shape == (display.height, display.width, 3)
        assert display.stride >= display.width * display.bpp // 8
    finally:
        display.close()


# ---------------------------------------------------------------- fluorosim screenshot

def write_appliance_profile(folder, bpp=32, width=64, height=48):
    (folder / "appliance.yaml").write_text(f"""\
fluoroscope: fluoroscopes/generic-ii-carm.yaml
case: cases/child-torso-vcug.yaml
phantom: phantoms/box-v1.yaml
keymap: keymaps/usb-numeric-keypad.yaml
devices:
  camera:
    source: synthetic
    webcam: webcams/generic-720p.yaml
  keypad:
    source: none
  display:
    target: file
    path: screen/screen.raw
    width: {width}
    height: {height}
    bpp: {bpp}
data_dir: var
""")
    return folder / "appliance.yaml"


@pytest.mark.parametrize("bpp", [24, 32])
def test_screenshot_writes_what_the_screen_file_shows(tmp_path, bpp, capsys):
    import cv2

    from appliance.cli import main
    config = write_appliance_profile(tmp_path, bpp=bpp)
    (tmp_path / "var" / "screen").mkdir(parents=True)
    frame = random_frame(48, 64)
    with FileDisplay(str(tmp_path / "var" / "screen" / "screen.raw"), 64, 48, bpp) as display:
        display.show(frame)
        out = tmp_path / "shot.png"
        assert main(["screenshot", str(out), "--config", str(config)]) == 0
    png = cv2.cvtColor(cv2.imread(str(out), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(png, frame)
    assert "64x48" in capsys.readouterr().out


def test_screenshot_problems_are_one_line(tmp_path, capsys):
    from appliance.cli import main
    config = write_appliance_profile(tmp_path)
    assert main(["screenshot", str(tmp_path / "shot.png"), "--config", str(config)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "screen.raw: no screen file" in err and "devices.display" in err
    assert not (tmp_path / "shot.png").exists()
    assert main(["screenshot", str(tmp_path / "shot.jpg"), "--config", str(config)]) == 2
    assert "as PNG" in capsys.readouterr().err
    assert main(["screenshot", str(tmp_path / "shot.png"), "--config", str(tmp_path / "none.yaml")]) == 2
    assert "none.yaml: no such appliance profile" in capsys.readouterr().err


FULL_DISK_SCRIPT = r"""
import sys
sys.path.insert(0, sys.argv[2])
from drivers.framebuffer import DisplayError, FileDisplay
try:
    FileDisplay(sys.argv[1] + "/screen.raw", 640, 480, 32)   # 1.2 MB on a 256 KiB file system
except DisplayError as e:
    print("DisplayError:", e)
"""


def test_a_full_disk_is_an_error_not_a_crash(tmp_path):
    # A real full file system: a 256 KiB tmpfs in a private mount namespace.
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare (util-linux) to make a small private file system")
    mnt = tmp_path / "small"
    mnt.mkdir()
    script = tmp_path / "full.py"
    script.write_text(FULL_DISK_SCRIPT)
    repo = str(Path(__file__).resolve().parents[1])
    import sys
    cmd = f"mount -t tmpfs -o size=256k tmpfs {mnt} && exec {sys.executable} {script} {mnt} {repo}"
    result = subprocess.run([unshare, "-rm", "sh", "-c", cmd], capture_output=True, text=True, timeout=60)
    if result.returncode != 0 and "mount" in result.stderr:
        pytest.skip(f"cannot mount a private tmpfs here: {result.stderr.strip()}")
    assert result.returncode == 0, result.stderr
    assert "screen.raw: cannot reserve 1228800 bytes" in result.stdout and "free disk space" in result.stdout
