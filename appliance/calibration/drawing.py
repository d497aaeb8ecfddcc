"""The workshop drawing of the sphere phantom: A4 at 1:1, as PDF (two pages) and PNG.

Page 1: plan view of both plates (balls of the top plate solid, of the bottom plate as
rings), every ball numbered, row and column positions dimensioned, the ArUco marker
placed, and a side view with the plate positions. Page 2: the table of every ball
(id, line, x, y, z, diameter), the numbers the calibration uses. Printed at 100 % the
plan view can be laid on the plate to centre-punch the holes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ..atomic_file import write_atomic
from ..config.calibration_phantom import CalibrationPhantomProfile

DPI = 300
A4_MM = (210.0, 297.0)
PX_PER_MM = DPI / 25.4


def _font(size_mm: float) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    return ImageFont.load_default(size=max(8, int(size_mm * PX_PER_MM)))


class _Sheet:
    """An A4 page with millimetre coordinates: (x right, y down) from the top-left corner."""

    def __init__(self):
        self.image = Image.new("L", (round(A4_MM[0] * PX_PER_MM), round(A4_MM[1] * PX_PER_MM)), 255)
        self.draw = ImageDraw.Draw(self.image)

    @staticmethod
    def px(x_mm: float, y_mm: float) -> tuple[float, float]:
        return x_mm * PX_PER_MM, y_mm * PX_PER_MM

    def line(self, a, b, width_mm=0.25, fill=0):
        self.draw.line([self.px(*a), self.px(*b)], fill=fill, width=max(1, round(width_mm * PX_PER_MM)))

    def rect(self, a, b, width_mm=0.35):
        (x0, y0), (x1, y1) = self.px(*a), self.px(*b)
        self.draw.rectangle([min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)], outline=0, width=max(1, round(width_mm * PX_PER_MM)))

    def circle(self, c, r_mm, filled: bool):
        (x, y), r = self.px(*c), r_mm * PX_PER_MM
        if filled:
            self.draw.ellipse([x - r, y - r, x + r, y + r], fill=0)
        else:
            self.draw.ellipse([x - r, y - r, x + r, y + r], outline=0, width=max(1, round(0.3 * PX_PER_MM)))

    def text(self, at, s, size_mm=2.5, anchor="la"):
        self.draw.text(self.px(*at), s, fill=0, font=_font(size_mm), anchor=anchor)


def _fmt(v: float) -> str:
    return f"{v:g}"


def plan_page(phantom: CalibrationPhantomProfile) -> Image.Image:
    sheet = _Sheet()
    sheet.text((15, 12), f"{phantom.name} - workshop drawing, scale 1:1 on A4 (print at 100 %)", 4.0)
    sheet.text((15, 19), "Plan view from the top plate (+z toward the reader). Solid: ball in the top plate; "
                         "ring: ball in the bottom plate. All dimensions in mm from the phantom origin.", 2.4)
    centres, diam = phantom.centres(), phantom.diameters()
    length = max(p.length_mm for p in phantom.plates)
    width = max(p.width_mm for p in phantom.plates)
    origin = (A4_MM[0] / 2 + 8, 30 + width / 2 + 8)  # sheet position of phantom (0, 0); phantom +y drawn upward

    def at(x, y):
        # y up on the sheet with x to the right keeps +z toward the reader: the view from above.
        return origin[0] + x, origin[1] - y

    top_z = max(p.centre_z_mm for p in phantom.plates)
    for s, c, d in zip(phantom.spheres, centres, diam):
        top = np.isclose(c[2], top_z)
        sheet.circle(at(c[0], c[1]), d / 2, filled=top)
        sheet.text(at(c[0] + d / 2 + 0.6, c[1] + d / 2 + 0.6), str(s.id), 2.0, anchor="ld")
    # Row positions on the left, column positions above, each with its extension line.
    left = origin[0] - length / 2 - 4
    for y in sorted(set(centres[:, 1])):
        labels = sorted({s.line for s, c in zip(phantom.spheres, centres) if c[1] == y})
        sheet.line(at(-length / 2 - 2, y), at(min(centres[centres[:, 1] == y, 0]) - 3, y), 0.15, fill=128)
        sheet.text((left, origin[1] - y), f"{'/'.join(labels)}  y = {_fmt(y)}", 2.2, anchor="rm")
    xs = sorted(set(centres[:, 0]))
    for i, x in enumerate(xs):
        y_text = width / 2 + 3 + 4 * (i % 2)
        sheet.line(at(x, width / 2), at(x, y_text - 1), 0.15, fill=128)
        sheet.text(at(x, y_text), _fmt(x), 2.2, anchor="ms")
    sheet.text(at(0, width / 2 + 12), "x positions of ball centres", 2.2, anchor="ms")
    # The outline last, so no grey extension line breaks it.
    sheet.rect(at(-length / 2, -width / 2), at(length / 2, width / 2))
    # Axes from the origin, leaving out the ball that may sit on it.
    sheet.line(at(2.5, 0), at(12, 0), 0.3)
    sheet.line(at(0, 2.5), at(0, 12), 0.3)
    sheet.text(at(13, 0), "x", 2.5, anchor="lm")
    sheet.text(at(0, 13), "y", 2.5, anchor="ms")
    # The marker: its outline and id where it is glued.
    T = phantom.T_phantom_from_marker()
    h = phantom.marker.size_mm / 2
    corners = [T[:2, :2] @ np.array(p) + T[:2, 3] for p in ((-h, -h), (h, -h), (h, h), (-h, h))]
    for a, b in zip(corners, corners[1:] + corners[:1]):
        sheet.line(at(*a), at(*b), 0.35)
    sheet.text(at(*T[:2, 3]), f"ArUco {phantom.marker.aruco_dictionary} id {phantom.marker.id}, "
                              f"{_fmt(phantom.marker.size_mm)} mm", 2.2, anchor="mm")
    sheet.text(at(-length / 2, -width / 2 - 3), f"plates {_fmt(length)} x {_fmt(width)} mm, PMMA; balls: steel, "
                                               f"{' and '.join(_fmt(d) for d in sorted(set(diam), reverse=True))} mm", 2.4)

    # Side view: plates along z, balls at their depths (looking along +y).
    base_y = origin[1] + width / 2 + 46
    sheet.text((15, base_y - 34), "Side view (looking along +y): plate mid-planes and ball centres, z up.", 2.4)
    for p in phantom.plates:
        z0, z1 = p.centre_z_mm - p.thickness_mm / 2, p.centre_z_mm + p.thickness_mm / 2
        sheet.rect((origin[0] - p.length_mm / 2, base_y - z1), (origin[0] + p.length_mm / 2, base_y - z0), 0.3)
        sheet.text((origin[0] + p.length_mm / 2 + 3, base_y - p.centre_z_mm),
                   f"{p.name}: mid-plane z = {_fmt(p.centre_z_mm)}, {_fmt(p.thickness_mm)} thick", 2.2, anchor="lm")
    for c, d in zip(centres, diam):
        sheet.circle((origin[0] + c[0], base_y - c[2]), d / 2, filled=True)
    sheet.line((origin[0] - length / 2 - 6, base_y), (origin[0] + length / 2 + 2, base_y), 0.15, fill=128)
    sheet.text((origin[0] - length / 2 - 7, base_y), "z = 0", 2.2, anchor="rm")
    return sheet.image


def table_page(phantom: CalibrationPhantomProfile) -> Image.Image:
    sheet = _Sheet()
    sheet.text((15, 12), f"{phantom.name} - ball positions (mm, phantom frame)", 4.0)
    cols = (20, 35, 50, 75, 100, 125)
    header = ("id", "line", "x", "y", "z", "diameter")
    for x, h in zip(cols, header):
        sheet.text((x, 25), h, 2.8)
    for i, s in enumerate(phantom.spheres):
        y = 32 + 6.2 * i
        values = (str(s.id), s.line, *(_fmt(v) for v in s.centre_mm), _fmt(s.diameter_mm))
        for x, v in zip(cols, values):
            sheet.text((x, y), v, 2.8)
    return sheet.image


def write_drawing(phantom: CalibrationPhantomProfile, out: Path) -> list[Path]:
    """Write OUT.pdf (two A4 pages) and OUT.png (the plan page); returns the paths."""
    import io

    out = Path(out)
    stem = out.with_suffix("") if out.suffix.lower() in (".pdf", ".png") else out
    plan, table = plan_page(phantom), table_page(phantom)
    pdf, png = io.BytesIO(), io.BytesIO()
    plan.save(pdf, "PDF", resolution=DPI, save_all=True, append_images=[table])
    plan.save(png, "PNG", dpi=(DPI, DPI))
    return [write_atomic(stem.with_suffix(".pdf"), pdf.getvalue()), write_atomic(stem.with_suffix(".png"), png.getvalue())]
