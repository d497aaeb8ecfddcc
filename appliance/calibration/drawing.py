"""The workshop drawing of the sphere phantom at 1:1 on A4, as PDF, PNG and CSV.

The plan: both plates seen from above (balls of the top plate solid, of the bottom plate as
rings), every ball numbered, row and column positions dimensioned, the ArUco marker placed,
and a side view with the plate positions. Printed at 100 % it can be laid on the plate to
centre-punch the holes. Then the table of every ball (id, line, x, y, z, diameter), the
numbers the calibration uses, over as many pages as it takes, and the same table as CSV for a
CNC drill.

A phantom whose plan does not fit one A4 page at 1:1 (the 200 mm grid plate) is not shrunk
silently: page 1 is an overview at the scale that fits, saying so and that it is not for
punching, and the plan follows at 1:1 in tiles, each within the printer's margins, overlapping
its neighbours so the balls line them up, with grey crosses every 50 mm of the phantom's x and
y and the phantom coordinates the tile covers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ..atomic_file import write_atomic
from ..config.calibration_phantom import CalibrationPhantomProfile

DPI = 300
A4_MM = (210.0, 297.0)
PX_PER_MM = DPI / 25.4
#: The plan fits A4 at 1:1 when the plate and its row labels leave this much on either side (mm).
A4_SIDE_MM = 30.0
#: Room on a tiled plan for the row labels left of the plate and beside its right edge (mm).
LABELS_LEFT_MM, LABELS_RIGHT_MM = 40.0, 10.0
#: Printers leave the sheet's edge unprinted: a tile's plan keeps this far inside it (mm).
PRINT_MARGIN_MM = 10.0
#: Neighbouring tiles share this much of the plan, two lattice pitches of the grid phantom (mm).
TILE_OVERLAP_MM = 20.0
#: Grey registration crosses on a tiled plan every this much of the phantom's x and y (mm).
CROSS_PITCH_MM = 50.0
#: Rows of the ball table on one page (its rows are 6.2 mm apart from 32 mm down).
TABLE_ROWS_PER_PAGE = 40


def _font(size_mm: float) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    return ImageFont.load_default(size=max(8, int(size_mm * PX_PER_MM)))


class _Sheet:
    """A page (A4 unless told) with millimetre coordinates: (x right, y down) from the top-left corner."""

    def __init__(self, size_mm: tuple[float, float] = A4_MM):
        self.image = Image.new("L", (round(size_mm[0] * PX_PER_MM), round(size_mm[1] * PX_PER_MM)), 255)
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


def _pixel(x_mm: float, y_mm: float) -> tuple[int, int]:
    """The whole pixel at a sheet position, where an image is pasted."""
    return round(x_mm * PX_PER_MM), round(y_mm * PX_PER_MM)


def _fmt(v: float) -> str:
    return f"{v:g}"


def fits_a4(phantom: CalibrationPhantomProfile) -> bool:
    """Whether the plan fits one A4 page at 1:1, its row labels beside the plate."""
    return max(p.length_mm for p in phantom.plates) + 2 * A4_SIDE_MM <= A4_MM[0]


def _plan_layout(phantom: CalibrationPhantomProfile) -> tuple[tuple[float, float], tuple[float, float]]:
    """(sheet size, sheet position of the phantom's origin), mm: A4 when the plan fits it, else a
    sheet as large as the plan needs, to be printed in tiles."""
    length = max(p.length_mm for p in phantom.plates)
    width = max(p.width_mm for p in phantom.plates)
    origin_y = 30 + width / 2 + 8
    if fits_a4(phantom):
        return A4_MM, (A4_MM[0] / 2 + 8, origin_y)
    # No side view on a tiled plan (the table gives every z): the plate and its labels alone.
    return (LABELS_LEFT_MM + length + LABELS_RIGHT_MM, origin_y + width / 2 + 12), (LABELS_LEFT_MM + length / 2, origin_y)


def plan_page(phantom: CalibrationPhantomProfile, tiles: int = 1) -> Image.Image:
    """The plan at 1:1: an A4 page, or, for a plate too large for one, the sheet `tiles` A4
    pages will carry."""
    size, origin = _plan_layout(phantom)
    sheet = _Sheet(size)
    where = "on A4" if tiles == 1 else f"over {tiles} A4 tiles"
    sheet.text((15, 12), f"{phantom.name} - workshop drawing, scale 1:1 {where} (print at 100 %)", 4.0)
    sheet.text((15, 19), "Plan view from the top plate (+z toward the reader). Solid: ball in the top plate; "
                         "ring: ball in the bottom plate. All dimensions in mm from the phantom origin.", 2.4)
    centres, diam = phantom.centres(), phantom.diameters()
    length = max(p.length_mm for p in phantom.plates)
    width = max(p.width_mm for p in phantom.plates)

    def at(x, y):
        # y up on the sheet with x to the right keeps +z toward the reader: the view from above.
        return origin[0] + x, origin[1] - y

    if tiles > 1:
        # Crosses clear of every ball, for lining up the tiles and checking the print's scale.
        for x in np.arange(-(length // 2 // CROSS_PITCH_MM) * CROSS_PITCH_MM, length / 2 + 1e-9, CROSS_PITCH_MM):
            for y in np.arange(-(width // 2 // CROSS_PITCH_MM) * CROSS_PITCH_MM, width / 2 + 1e-9, CROSS_PITCH_MM):
                if np.hypot(centres[:, 0] - x, centres[:, 1] - y).min() > 4.0:
                    sheet.line(at(x - 3, y), at(x + 3, y), 0.2, fill=128)
                    sheet.line(at(x, y - 3), at(x, y + 3), 0.2, fill=128)
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

    if tiles > 1:
        return sheet.image
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


@dataclass(frozen=True)
class Tile:
    """One A4 page of a plan printed in tiles: where on it the plan's window lies, and what the
    window covers in the phantom frame (mm)."""

    page: Image.Image
    row: int
    column: int
    x_range_mm: tuple[float, float]   # phantom x at the window's left and right edges
    y_range_mm: tuple[float, float]   # phantom y at its top and bottom edges


def tile_windows(phantom: CalibrationPhantomProfile) -> list[tuple[int, int, float, float]]:
    """(row, column, sheet x, sheet y) of each tile's top-left corner on the plan's sheet (mm)."""
    (w, h), _ = _plan_layout(phantom)
    inner = (A4_MM[0] - 2 * PRINT_MARGIN_MM, A4_MM[1] - 2 * PRINT_MARGIN_MM)

    def starts(total: float, window: float) -> list[float]:
        step = window - TILE_OVERLAP_MM
        n = max(1, int(np.ceil((total - TILE_OVERLAP_MM) / step)))
        return [i * step for i in range(n)]

    return [(r, c, x, y) for r, y in enumerate(starts(h, inner[1])) for c, x in enumerate(starts(w, inner[0]))]


def tile_pages(phantom: CalibrationPhantomProfile, plan: Image.Image | None = None) -> list[Tile]:
    """The 1:1 plan (`plan_page` with its tile count, drawn here unless given) cut into A4 pages,
    each window PRINT_MARGIN_MM inside its page's edge."""
    windows = tile_windows(phantom)
    plan = plan or plan_page(phantom, tiles=len(windows))
    _, origin = _plan_layout(phantom)
    inner = (A4_MM[0] - 2 * PRINT_MARGIN_MM, A4_MM[1] - 2 * PRINT_MARGIN_MM)
    rows, cols = max(w[0] for w in windows) + 1, max(w[1] for w in windows) + 1
    tiles = []
    for n, (r, c, x, y) in enumerate(windows, start=1):
        sheet = _Sheet()
        left, top, right, bottom = (round(v * PX_PER_MM) for v in (x, y, x + inner[0], y + inner[1]))
        # The last row and column reach past the plan's sheet: white there, not the crop's black.
        sheet.image.paste(plan.crop((left, top, min(right, plan.width), min(bottom, plan.height))),
                          _pixel(PRINT_MARGIN_MM, PRINT_MARGIN_MM))
        sheet.rect((PRINT_MARGIN_MM, PRINT_MARGIN_MM), (A4_MM[0] - PRINT_MARGIN_MM, A4_MM[1] - PRINT_MARGIN_MM), 0.1)
        xs = (x - origin[0], x + inner[0] - origin[0])
        ys = (origin[1] - y, origin[1] - y - inner[1])
        sheet.text((PRINT_MARGIN_MM, A4_MM[1] - PRINT_MARGIN_MM + 2),
                   f"{phantom.name}, plan at 1:1, tile {n} of {len(windows)} (row {r + 1} of {rows}, column {c + 1} of "
                   f"{cols}): phantom x {_fmt(round(xs[0], 1))} to {_fmt(round(xs[1], 1))} mm, y {_fmt(round(ys[0], 1))} "
                   f"to {_fmt(round(ys[1], 1))} mm; overlaps its neighbours by {_fmt(TILE_OVERLAP_MM)} mm", 2.2)
        tiles.append(Tile(sheet.image, r, c, xs, ys))
    return tiles


def overview_page(phantom: CalibrationPhantomProfile, plan: Image.Image, tiles: int, table_pages: int) -> Image.Image:
    """The whole plan (`plan_page`) shrunk onto one A4 page, saying its scale and where the 1:1 pages are."""
    (w, h), _ = _plan_layout(phantom)
    room = (A4_MM[0] - 2 * PRINT_MARGIN_MM, A4_MM[1] - 2 * PRINT_MARGIN_MM - 14)
    scale = min(room[0] / w, room[1] / h)
    sheet = _Sheet()
    sheet.text((PRINT_MARGIN_MM, 12), f"{phantom.name} - overview at {scale:.0%} of full size: NOT to scale, do not "
                                      f"punch or measure from this page", 3.2)
    sheet.text((PRINT_MARGIN_MM, 18), f"Pages 2-{tiles + 1}: the plan at 1:1 in {tiles} tiles (print at 100 %). Pages "
                                      f"{tiles + 2}-{tiles + 1 + table_pages}: every ball's position (z: its plate); the "
                                      f"same in the CSV file for a CNC drill.", 2.4)
    small = plan.resize((round(w * scale * PX_PER_MM), round(h * scale * PX_PER_MM)), Image.Resampling.LANCZOS)
    sheet.image.paste(small, _pixel(PRINT_MARGIN_MM, PRINT_MARGIN_MM + 14))
    return sheet.image


def table_pages(phantom: CalibrationPhantomProfile) -> list[Image.Image]:
    """Every ball's id, line, position and diameter, TABLE_ROWS_PER_PAGE to a page."""
    pages = []
    spheres = phantom.spheres
    count = max(1, int(np.ceil(len(spheres) / TABLE_ROWS_PER_PAGE)))
    cols = (20, 35, 50, 75, 100, 125)
    header = ("id", "line", "x", "y", "z", "diameter")
    for page in range(count):
        sheet = _Sheet()
        part = f", page {page + 1} of {count}" if count > 1 else ""
        sheet.text((15, 12), f"{phantom.name} - ball positions (mm, phantom frame){part}", 4.0)
        for x, h in zip(cols, header):
            sheet.text((x, 25), h, 2.8)
        for i, s in enumerate(spheres[page * TABLE_ROWS_PER_PAGE:(page + 1) * TABLE_ROWS_PER_PAGE]):
            y = 32 + 6.2 * i
            values = (str(s.id), s.line, *(_fmt(v) for v in s.centre_mm), _fmt(s.diameter_mm))
            for x, v in zip(cols, values):
                sheet.text((x, y), v, 2.8)
        pages.append(sheet.image)
    return pages


def ball_csv(phantom: CalibrationPhantomProfile) -> str:
    rows = ["id,line,x_mm,y_mm,z_mm,diameter_mm"]
    rows += [",".join((str(s.id), s.line, *(_fmt(v) for v in s.centre_mm), _fmt(s.diameter_mm))) for s in phantom.spheres]
    return "\n".join(rows) + "\n"


def drawing_pages(phantom: CalibrationPhantomProfile) -> list[Image.Image]:
    """Every A4 page in order: the plan (or an overview and its 1:1 tiles), then the table."""
    table = table_pages(phantom)
    if fits_a4(phantom):
        return [plan_page(phantom), *table]
    plan = plan_page(phantom, tiles=len(tile_windows(phantom)))
    tiles = tile_pages(phantom, plan)
    return [overview_page(phantom, plan, len(tiles), len(table)), *(t.page for t in tiles), *table]


def write_drawing(phantom: CalibrationPhantomProfile, out: Path) -> list[Path]:
    """Write OUT.pdf (every page), OUT.png (the first page) and OUT.csv (the ball table); returns the paths."""
    import io

    out = Path(out)
    stem = out.with_suffix("") if out.suffix.lower() in (".pdf", ".png", ".csv") else out
    pages = drawing_pages(phantom)
    pdf, png = io.BytesIO(), io.BytesIO()
    pages[0].save(pdf, "PDF", resolution=DPI, save_all=True, append_images=pages[1:])
    pages[0].save(png, "PNG", dpi=(DPI, DPI))
    return [write_atomic(stem.with_suffix(".pdf"), pdf.getvalue()), write_atomic(stem.with_suffix(".png"), png.getvalue()),
            write_atomic(stem.with_suffix(".csv"), ball_csv(phantom).encode("utf-8"))]
