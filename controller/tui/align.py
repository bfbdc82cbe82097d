"""Align screen: probe plan, probed points and plane fits with residuals, leveling, apply."""
from __future__ import annotations

from typing import Any

from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import DataTable, Static

from controller.tui.widgets import fmt, put
from controller.tui.session import View


class AlignPane(Vertical):
    """Probe-and-align on the CNC (press l to run, y to apply the transform to the job)."""

    DEFAULT_CSS = """
    AlignPane #align-head { height: auto; margin-bottom: 1; }
    AlignPane DataTable { height: auto; max-height: 10; margin-bottom: 1; }
    AlignPane #align-result { height: auto; }
    """

    def __init__(self) -> None:
        super().__init__(id="align-pane")
        self._key: object = None

    def compose(self) -> ComposeResult:
        yield Static("", id="align-head")
        yield DataTable(id="align-points", cursor_type="none")
        yield DataTable(id="align-planes", cursor_type="none")
        yield Static("", id="align-result")

    def on_mount(self) -> None:
        self.query_one("#align-points", DataTable).add_columns("face", "x mm", "y mm", "z mm", "residual mm")
        self.query_one("#align-planes", DataTable).add_columns("plane", "points", "normal", "rms mm", "max mm",
                                                                "outliers")

    def refresh_view(self, v: View) -> None:
        put(self.query_one("#align-head", Static), _headline(v))
        key = (id(v.alignment), v.probe_plan, len(v.probed))
        if key == self._key:
            return
        self._key = key
        a = v.alignment or {}
        planes = _planes(a)
        _fill_points(self.query_one("#align-points", DataTable), planes, v)
        _fill_planes(self.query_one("#align-planes", DataTable), planes)
        put(self.query_one("#align-result", Static), "\n".join(_result_lines(a)))


def _headline(v: View) -> str:
    if not v.can_probe:
        return ("Alignment probes the substrate with the touch probe on the 5-axis CNC. This cell has none "
                f"(it deposits with the [b]{v.platform}[/b] in its own frame): no alignment is needed.")
    if v.busy == "aligning":
        return (f"[yellow]Probing…[/] {len(v.probed)} of {len(v.probe_plan) or '?'} touches so far "
                "(top grid, side face, third face; the top is probed again after leveling).")
    if v.alignment is None:
        return "Not aligned. Press [b]l[/b] to probe the top and side faces and fit the planes."
    return "[green]Aligned.[/] Press [b]y[/b] to apply the transform to the open job."


def _planes(a: dict[str, Any]) -> list[dict[str, Any]]:
    """The alignment's planes as a list (a dict of them is keyed by name)."""
    planes = a.get("planes") or []
    if isinstance(planes, dict):
        planes = [dict(p, name=k) for k, p in planes.items()]
    return list(planes)


def _fill_points(pts: DataTable[str], planes: list[dict[str, Any]], v: View) -> None:
    """The fitted planes' points with residuals; else the touches so far; else the probe plan."""
    pts.clear()
    shown = 0
    for i, pl in enumerate(planes):
        name = str(pl.get("name", f"plane {i + 1}"))
        residuals = pl.get("residuals") or []
        for k, p in enumerate(pl.get("points") or []):
            res = residuals[k] if k < len(residuals) else None
            pts.add_row(name, fmt(p[0], 3), fmt(p[1], 3), fmt(p[2], 3), fmt(res, 4))
            shown += 1
    if not shown and v.probed:
        for name, xyz, spread in v.probed:
            pts.add_row(name, fmt(xyz[0], 3), fmt(xyz[1], 3), fmt(xyz[2], 3), f"[dim]spread {fmt(spread, 4)}[/]")
        pts.move_cursor(row=pts.row_count - 1)
        shown = len(v.probed)
    if not shown:
        for face, xyz in v.probe_plan:
            pts.add_row(face, fmt(xyz[0], 3), fmt(xyz[1], 3), fmt(xyz[2], 3), "[dim]planned[/]")


def _fill_planes(pl_t: DataTable[str], planes: list[dict[str, Any]]) -> None:
    pl_t.clear()
    for i, pl in enumerate(planes):
        n = pl.get("normal") or [None, None, None]
        pl_t.add_row(str(pl.get("name", f"plane {i + 1}")), str(pl.get("n_points", len(pl.get("points") or []))),
                     "(" + ", ".join(fmt(c, 5) for c in n) + ")", fmt(pl.get("rms_mm"), 4),
                     fmt(pl.get("max_residual_mm"), 4), str(len(pl.get("outliers") or [])))


def _result_lines(a: dict[str, Any]) -> list[str]:
    """Leveling angles, the second face's angle and the transform, one per line."""
    lines: list[str] = []
    if a:
        lines.append(f"leveling  A {fmt(a.get('level_a_deg'), 4)}°   B {fmt(a.get('level_b_deg'), 4)}°")
        if a.get("face_angle_deg") is not None:
            lines.append(f"second face angle  {fmt(a.get('face_angle_deg'), 4)}°")
        tf = a.get("transform")
        if tf:
            lines.append("transform (CAD → machine):")
            lines += ["  [" + "  ".join(f"{c:10.5f}" for c in row) + "]" for row in tf]
    return lines
