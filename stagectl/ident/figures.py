"""Small raster figures for the discovery report, drawn with Pillow directly.

`stagectl discover` writes three diagnostic PNGs (residual over time, by regime, by position and velocity).
Drawn with matplotlib they cost about 0.6 s of CPU (0.3 s to import it, 0.3 s to build and draw tick and text
objects), a sixth of the whole command on the EMPS pair; these plots need lines, dots, bars, axes with
ticks, titles and legends, which Pillow (already installed with matplotlib) draws in a few hundredths of a
second. Drawn at twice the size and reduced with a box filter, so lines and text are anti-aliased.

Coordinates: a :class:`Panel` maps data (x, y) to pixels of its box; NaN in a line's y breaks the line.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
from PIL import Image, ImageDraw, ImageFont

FloatArray = npt.NDArray[np.float64]

#: supersampling factor (drawn at this multiple of the output size, then reduced)
SS = 2
#: matplotlib's default colour cycle (tab10), so the series keep their familiar colours
COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728")
_GRID = (225, 225, 225)


def _font(size_px: float) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    return ImageFont.load_default(size_px * SS)


def nice_ticks(lo: float, hi: float, target: int = 8) -> list[float]:
    """Ticks at 1, 2 or 5 times a power of ten covering ``[lo, hi]``, about ``target`` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / max(target - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9)
    out = []
    k = first
    while k * step <= hi + 1e-9 * step:
        out.append(k * step)
        k += 1
    return out


def tick_label(v: float, step: float) -> str:
    """Tick text with as many decimals as the step needs (``0`` never written as ``-0``)."""
    if v == 0 or abs(v) < 1e-12 * max(step, 1e-300):
        return "0"
    if abs(v) >= 1e5 or abs(v) < 1e-3:
        return f"{v:.3g}"
    dec = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 3
    if step > 0 and abs(step * 10**dec - round(step * 10**dec)) > 1e-6:
        dec += 1  # 2.5-type steps
    return f"{v:.{dec}f}"


class Figure:
    """A white canvas of ``width`` x ``height`` output pixels."""

    def __init__(self, width: int, height: int) -> None:
        self.size = (width, height)
        self.img = Image.new("RGB", (width * SS, height * SS), "white")
        self.draw = ImageDraw.Draw(self.img)

    def panel(self, left: float, top: float, right: float, bottom: float) -> Panel:
        """A panel whose plotting box spans the given fractions of the figure (from its top-left corner)."""
        w, h = self.img.size
        return Panel(self, (left * w, top * h, right * w, bottom * h))

    def text(self, xy: tuple[float, float], s: str, size: float = 10, anchor: str = "la",
             fill: str | tuple[int, int, int] = "black") -> None:
        self.draw.text(xy, s, font=_font(size), fill=fill, anchor=anchor)

    def vtext(self, xy: tuple[float, float], s: str, size: float = 10) -> None:
        """Text rotated by 90° (reading upwards), centred on ``xy``."""
        f = _font(size)
        l, t, r, b = f.getbbox(s)
        im = Image.new("L", (int(r - l) + 2, int(b - t) + 2), 0)
        ImageDraw.Draw(im).text((1 - l, 1 - t), s, font=f, fill=255)
        im = im.rotate(90, expand=True)
        x, y = int(xy[0] - im.size[0] / 2), int(xy[1] - im.size[1] / 2)
        self.img.paste((0, 0, 0), (x, y, x + im.size[0], y + im.size[1]), im)

    def save(self, path: Path) -> None:
        self.img.reduce(SS).save(path, compress_level=1)


class Panel:
    """One set of axes: data limits, the box in canvas pixels, and the drawing calls."""

    def __init__(self, fig: Figure, box: tuple[float, float, float, float]) -> None:
        self.fig = fig
        self.box = box
        self.xlim = (0.0, 1.0)
        self.ylim = (0.0, 1.0)
        self.legend_items: list[tuple[str, str, str]] = []

    def limits(self, xs: Sequence[FloatArray], ys: Sequence[FloatArray], margin: float = 0.05) -> None:
        """Data limits covering the finite values of ``xs`` and ``ys``, widened by ``margin`` on each side."""
        def span(arrs: Sequence[FloatArray]) -> tuple[float, float]:
            vals = [a[np.isfinite(a)] for a in arrs]
            vals = [v for v in vals if v.size]
            if not vals:
                return 0.0, 1.0
            lo = min(float(v.min()) for v in vals)
            hi = max(float(v.max()) for v in vals)
            if hi <= lo:
                lo, hi = lo - 0.5, hi + 0.5
            d = margin * (hi - lo)
            return lo - d, hi + d
        self.xlim = span(xs)
        self.ylim = span(ys)

    def _px(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        x0, y0, x1, y1 = self.box
        px = x0 + (np.asarray(x, float) - self.xlim[0]) / (self.xlim[1] - self.xlim[0]) * (x1 - x0)
        py = y1 - (np.asarray(y, float) - self.ylim[0]) / (self.ylim[1] - self.ylim[0]) * (y1 - y0)
        return px, py

    def line(self, x: FloatArray, y: FloatArray, color: str, width: float = 1.0, label: str | None = None) -> None:
        """A polyline through the points; NaN in ``y`` leaves a gap."""
        px, py = self._px(x, y)
        ok = np.isfinite(px) & np.isfinite(py)
        if not ok.any():
            return
        # runs of finite points, each drawn as one polyline
        edges = np.flatnonzero(np.diff(np.concatenate(([0], ok.view(np.int8), [0]))))
        w = max(1, round(width * SS))
        for a, b in zip(edges[::2], edges[1::2]):
            pts = np.column_stack((px[a:b], py[a:b])).ravel().tolist()
            if b - a == 1:
                pts = pts + pts
            self.fig.draw.line(pts, fill=color, width=w)
        if label:
            self.legend_items.append((label, color, "line"))

    def dots(self, x: FloatArray, y: FloatArray, color: str, label: str | None = None) -> None:
        """Small square dots (2 x 2 canvas pixels: one output pixel)."""
        px, py = self._px(x, y)
        ok = np.isfinite(px) & np.isfinite(py)
        ix = np.round(px[ok]).astype(int)
        iy = np.round(py[ok]).astype(int)
        for dx in range(SS):
            for dy in range(SS):
                self.fig.draw.point(np.column_stack((ix + dx, iy + dy)).ravel().tolist(), fill=color)
        if label:
            self.legend_items.append((label, color, "dot"))

    def hbars(self, y: FloatArray, widths: Sequence[float], height: float, color: str, label: str | None = None) -> None:
        """Horizontal bars from x = 0 to ``widths`` centred on ``y`` (``height`` in data units)."""
        for yy, ww in zip(y, widths):
            xa, ya = self._px(np.array([0.0, ww]), np.array([yy + height / 2, yy - height / 2]))
            self.fig.draw.rectangle((min(xa), min(ya), max(xa), max(ya)), fill=color)
        if label:
            self.legend_items.append((label, color, "box"))

    def grid(self, yticks: Sequence[float] | None = None) -> None:
        """Light grid lines at the ticks (call before drawing the data, so the data stay on top)."""
        d = self.fig.draw
        x0, y0, x1, y1 = self.box
        for v in nice_ticks(*self.xlim):
            px, _ = self._px(np.array([v]), np.array([0.0]))
            d.line((px[0], y0, px[0], y1), fill=_GRID, width=SS)
        for v in nice_ticks(*self.ylim) if yticks is None else yticks:
            _, py = self._px(np.array([self.xlim[0]]), np.array([v]))
            d.line((x0, py[0], x1, py[0]), fill=_GRID, width=SS)

    def axes(self, xlabel: str = "", ylabel: str = "", title: str = "", xticks: bool = True,
             yticklabels: Sequence[tuple[float, str]] | None = None, font: float = 10) -> None:
        """Frame, ticks with labels, axis labels and title."""
        d, f = self.fig.draw, self.fig
        x0, y0, x1, y1 = self.box
        tick = 4 * SS
        xs = nice_ticks(*self.xlim)
        xstep = xs[1] - xs[0] if len(xs) > 1 else 1.0
        for v in xs:
            px, _ = self._px(np.array([v]), np.array([0.0]))
            d.line((px[0], y1, px[0], y1 + tick), fill="black", width=SS)
            if xticks:
                f.text((px[0], y1 + tick + 2 * SS), tick_label(v, xstep), size=font - 1, anchor="ma")
        if yticklabels is None:
            ys = nice_ticks(*self.ylim)
            ystep = ys[1] - ys[0] if len(ys) > 1 else 1.0
            yticklabels = [(v, tick_label(v, ystep)) for v in ys]
        for v, lab in yticklabels:
            _, py = self._px(np.array([self.xlim[0]]), np.array([v]))
            d.line((x0 - tick, py[0], x0, py[0]), fill="black", width=SS)
            f.text((x0 - tick - 2 * SS, py[0]), lab, size=font - 1, anchor="rm")
        d.rectangle((x0, y0, x1, y1), outline="black", width=SS)
        if xlabel:
            f.text(((x0 + x1) / 2, y1 + tick + (font + 6) * SS), xlabel, size=font, anchor="ma")
        if ylabel:
            w = max((_font(font - 1).getlength(lab) for _, lab in yticklabels), default=0.0)
            f.vtext((x0 - tick - 4 * SS - w - (font - 2) * SS, (y0 + y1) / 2), ylabel, size=font)
        if title:
            f.text(((x0 + x1) / 2, y0 - 4 * SS), title, size=font + 2, anchor="md")

    def legend(self, font: float = 8, lower: bool = False) -> None:
        """The labelled series in a framed box at the upper (``lower``: lower) right."""
        if not self.legend_items:
            return
        d, fnt = self.fig.draw, _font(font)
        _, y0, x1, y1 = self.box
        line_h = (font + 5) * SS
        key = 18 * SS
        w = max(fnt.getlength(lab) for lab, _, _ in self.legend_items) + key + 10 * SS
        h = line_h * len(self.legend_items) + 6 * SS
        bx0, by0 = x1 - w - 6 * SS, (y1 - h - 6 * SS) if lower else (y0 + 6 * SS)
        d.rectangle((bx0, by0, bx0 + w, by0 + h), fill="white", outline=(190, 190, 190), width=SS)
        for i, (lab, color, kind) in enumerate(self.legend_items):
            cy = by0 + 3 * SS + line_h * (i + 0.5)
            kx = bx0 + 4 * SS
            if kind == "line":
                d.line((kx, cy, kx + key - 4 * SS, cy), fill=color, width=2 * SS)
            elif kind == "dot":
                m = kx + (key - 4 * SS) / 2
                d.rectangle((m - 2 * SS, cy - 2 * SS, m + 2 * SS, cy + 2 * SS), fill=color)
            else:
                d.rectangle((kx, cy - 3 * SS, kx + key - 4 * SS, cy + 3 * SS), fill=color)
            d.text((kx + key, cy), lab, font=fnt, fill="black", anchor="lm")
