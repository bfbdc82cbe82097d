"""Small widgets of the operator UI: a labelled sparkline, the layer preview drawn in braille."""
from __future__ import annotations

import math
import time
from typing import Hashable, Sequence

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Horizontal
from textual.widgets import Label, Sparkline, Static

ROLE_STYLE = {"perimeter": "bright_cyan", "infill": "yellow", "gap": "magenta"}
DONE_STYLE = "bright_green"

Path2 = tuple[tuple[float, float], ...]


def put(w: Static, text: str) -> None:
    """Show `text` in `w`, doing nothing when it is already shown.

    Textual redraws on every `update`, and an update that may change the widget's size lays
    the whole screen out again (with the interpreter lock held: the controller's device loop
    waits behind it; docs/tui.md, "The screen never holds up the devices"). So an unchanged
    text is not sent at all, and a changed one is laid out again only when the widget's size
    follows its text (an `auto` width or height).
    """
    old = w.content
    if isinstance(old, str) and old == text:
        return
    w.update(text, layout=w.styles.is_auto_width or w.styles.is_auto_height)


class Redraw:
    """When a table of live counters is drawn again: at once when what it shows changed in kind
    (`urgent`: a link up or down, a device added), otherwise at most once every `period_s`
    while its counters move. A table is cleared and filled again on a redraw, with the
    interpreter lock held (docs/tui.md, "The screen never holds up the devices")."""

    def __init__(self, period_s: float = 1.0) -> None:
        self.period_s = period_s
        self._key: Hashable = None
        self._urgent: Hashable = None
        self._at = -math.inf

    def due(self, key: Hashable, urgent: Hashable) -> bool:
        """True when the table showing `key` is to be drawn now (and it counts as drawn)."""
        if key == self._key:
            return False
        now = time.monotonic()
        if urgent == self._urgent and now - self._at < self.period_s:
            return False
        self._key, self._urgent, self._at = key, urgent, now
        return True


def fmt(v: float | None, nd: int = 1, unit: str = "") -> str:
    """A number for the screen, or an em dash when there is none."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    return f"{v:.{nd}f}{unit}"


class Trend(Horizontal):
    """A live value: name, latest reading, and a sparkline of its recent history."""

    DEFAULT_CSS = """
    Trend { height: 1; }
    Trend > .trend-name { width: 14; }
    Trend > .trend-value { width: 12; height: 1; text-align: right; padding-right: 1; }
    Trend > Sparkline { width: 1fr; }
    """

    def __init__(self, name: str, unit: str, nd: int = 1, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self._label, self._unit, self._nd = name, unit, nd

    def compose(self) -> ComposeResult:
        yield Label(self._label, classes="trend-name")
        yield Label("—", classes="trend-value")
        yield Sparkline([], summary_function=max)

    def show(self, value: float | None, history: Sequence[float | None]) -> None:
        put(self.query_one(".trend-value", Label), fmt(value, self._nd, " " + self._unit))
        data = [v for v in history if v is not None]
        spark = self.query_one(Sparkline)
        if list(spark.data or []) != data:
            spark.data = data


def braille(paths: Sequence[tuple[str, Path2]], bounds: tuple[float, float, float, float], cols: int, rows: int) -> Text:
    """Polylines drawn on a `cols` × `rows` character canvas of braille dots (2 × 4 per char).

    `paths` are (style, points); later paths draw over earlier ones. The scale is uniform
    (a terminal cell is about twice as tall as wide, a dot column half a cell wide and a dot
    row a quarter of a cell tall: about square) and y goes up.
    """
    w, h = cols * 2, rows * 4
    x0, y0, x1, y1 = bounds
    span = max(x1 - x0, (y1 - y0), 1e-9)
    s = min((w - 1) / span if x1 > x0 else math.inf, (h - 1) / span if y1 > y0 else math.inf)
    s = (w - 1) / span if not math.isfinite(s) else s
    ox = (w - 1 - (x1 - x0) * s) / 2
    oy = (h - 1 - (y1 - y0) * s) / 2
    dots: dict[tuple[int, int], str] = {}

    def plot(px: float, py: float, style: str) -> None:
        cx = int(round(ox + (px - x0) * s))
        cy = int(round(h - 1 - (oy + (py - y0) * s)))
        if 0 <= cx < w and 0 <= cy < h:
            dots[(cx, cy)] = style

    for style, pts in paths:
        for (ax, ay), (bx, by) in zip(pts, pts[1:]):
            n = max(1, int(math.hypot(bx - ax, by - ay) * s * 1.5))
            for k in range(n + 1):
                f = k / n
                plot(ax + (bx - ax) * f, ay + (by - ay) * f, style)
        if len(pts) == 1:
            plot(pts[0][0], pts[0][1], style)
    bits = ((0, 0, 0x01), (0, 1, 0x02), (0, 2, 0x04), (1, 0, 0x08), (1, 1, 0x10), (1, 2, 0x20), (0, 3, 0x40), (1, 3, 0x80))
    out = Text(no_wrap=True, overflow="crop")
    for r in range(rows):
        for c in range(cols):
            code, style = 0, ""
            for dx, dy, bit in bits:
                st = dots.get((c * 2 + dx, r * 4 + dy))
                if st is not None:
                    code |= bit
                    style = st
            out.append(chr(0x2800 + code) if code else " ", style=style or None)
        if r < rows - 1:
            out.append("\n")
    return out


def bounds_of(layers: Sequence[Sequence[tuple[str, Path2]]]) -> tuple[float, float, float, float]:
    xs = [p[0] for la in layers for _r, pts in la for p in pts]
    ys = [p[1] for la in layers for _r, pts in la for p in pts]
    if not xs:
        return (0.0, 0.0, 1.0, 1.0)
    return (min(xs), min(ys), max(xs), max(ys))


class LayerPreview(Static):
    """One layer of the job in the terminal: beads coloured by role, done beads in green."""

    DEFAULT_CSS = "LayerPreview { width: 1fr; height: 1fr; min-height: 8; }"

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__("", id=id)
        self._key: tuple[int, int | None, int, int, int, str] | None = None

    def show(self, layers: Sequence[Sequence[tuple[str, Path2]]], layer: int | None, done: int = 0,
             title: str = "") -> None:
        """Draw `layers[layer]`; its first `done` passes in the 'done' colour."""
        cols = max(10, self.size.width or 40)
        rows = max(4, (self.size.height or 12) - 1)
        key = (id(layers), layer, done, cols, rows, title)
        if key == self._key:
            return
        self._key = key
        if not layers or layer is None or not (0 <= layer < len(layers)):
            self.update(Text("no job open: press o to open a part or a job file", style="dim"), layout=False)
            return
        paths = [(DONE_STYLE if k < done else ROLE_STYLE.get(role, "white"), pts)
                 for k, (role, pts) in enumerate(layers[layer])]
        pic = braille(paths, bounds_of(layers), cols, rows)
        legend = Text(title + " ", style="bold", no_wrap=True, overflow="ellipsis")
        for role, st in ROLE_STYLE.items():
            legend.append("■", style=st).append(role + " ")
        if done:
            legend.append("■", style=DONE_STYLE).append("done")
        legend.truncate(cols, overflow="ellipsis")
        # its size is the screen's share (1fr), never its text's: no layout of the whole screen
        self.update(Text.assemble(legend, "\n", pic), layout=False)
