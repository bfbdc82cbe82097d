"""The CNC simulator's spindle and cutters: the tool in the spindle, its length, and what it cuts.

The tools are cell.yaml's (`tools:`): the deposition head with its touch probe (length 0, the
machine's reference) and the cutters, each as long as its `length_offset_mm` says (the truth the
simulator holds; the controller applies it as `G43.1 Z…`, or measures it on the tool setter). A
`T<n>` word selects a tool; `M6` (grblHAL) or the operator during an `M0` pause (grbl 1.1h) loads it.

With a cutter loaded every stretch of motion sweeps its tip through the workpiece's height map
(`HeightMap.carve`: deposit and stock alike). It cuts only with the spindle turning at a valid
speed (`M3 S` within the cutter's `max_rpm`, and `$32=0`: laser mode stops the spindle on
rapids); cutting metal with the spindle stopped, deeper than the flutes or into the table is a
tool breakage: `[MSG:Tool breakage: …]` then `ALARM:1` (docs/machining.md). Every cutting move is
a row of `cut.jsonl`: {"seq", "line", "tool", "from", "to" (part frame), "removed_mm3", "depth_mm", "t"}.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING

import numpy as np

from sims.heightmap import HeightMap

from sims.context import SimContext, attach

if TYPE_CHECKING:
    from core.tools import Tools
    from sims.cnc.block import Block, Pos5
    from sims.workpiece import Workpiece

TABLE_CLEAR_MM = 0.0     # the part's lowest point is on the table


@dataclass(frozen=True)
class SimTool:
    number: int
    kind: str                 # "probe" (the deposition head and its touch probe) | "flat" | "ball"
    radius_mm: float = 0.0
    flute_length_mm: float = 0.0
    max_rpm: float = 0.0
    length_mm: float = 0.0    # how far the tip reaches below the reference point


class Breakage(Exception):
    """A cut the tool cannot survive (the simulator raises the alarm)."""


def sim_tools(tools: Tools | None) -> dict[int, SimTool]:
    if tools is None:
        return {0: SimTool(0, "probe")}
    out = {tools.deposition.number: SimTool(tools.deposition.number, "probe",
                                            length_mm=tools.deposition.length_offset_mm)}
    for c in tools.cutters.values():
        out[c.number] = SimTool(c.number, c.type, c.radius_mm, c.flute_length_mm, c.max_rpm, c.length_offset_mm)
    return out


class Spindle:
    """The tool in the spindle and the cuts it makes (one per CNC simulator)."""

    def __init__(self, tools: dict[int, SimTool], workpiece: Workpiece | None, log_path: Path | None,
                 setter_mm: tuple[float, float, float] = (-150.0, -150.0, 0.0)) -> None:
        self.tools = tools
        self.loaded = min(n for n, t in tools.items() if t.kind == "probe") if tools else 0
        self.selected = self.loaded
        self.workpiece = workpiece
        self.setter = setter_mm
        self._log: IO[str] | None = open(log_path, "a", encoding="utf-8") if log_path is not None else None
        self._move: dict[str, float] = {}
        self._bottom: float | None = None
        self._mesh_top: float | None = None
        self.removed_mm3 = 0.0

    @property
    def tool(self) -> SimTool:
        return self.tools.get(self.loaded, SimTool(self.loaded, "probe"))

    @property
    def is_cutter(self) -> bool:
        return self.tool.kind in ("flat", "ball")

    def load_selected(self) -> None:
        self.loaded = self.selected

    def tip(self, pos: Pos5) -> tuple[float, float, float, float, float]:
        """The loaded tool's tip (machine frame) for a machine position."""
        return (pos[0], pos[1], pos[2] - self.tool.length_mm, pos[3], pos[4])

    def _map(self) -> HeightMap | None:
        wp = self.workpiece
        if wp is None:
            return None
        if wp.deposit_map is None:
            wp.deposit_map = HeightMap(0.5, wp.top_z)
        if wp.settle is not None:
            wp.settle()
        return wp.deposit_map

    def _table_z(self) -> float:
        if self._bottom is None and self.workpiece is not None:
            self._bottom = float(np.min(self.workpiece.vertices()[:, 2]))
        return self._bottom if self._bottom is not None else -1e9

    def moved(self, b: Block, p0: Pos5, p1: Pos5, turning: bool, rpm: float) -> None:
        """A stretch of motion with the loaded tool; raises Breakage for a cut it cannot survive."""
        if not self.is_cutter or self.workpiece is None:
            return
        hm = self._map()
        if hm is None:
            return
        q0, _ = self.workpiece.part_frame(self.tip(p0))
        q1, _ = self.workpiece.part_frame(self.tip(p1))
        tool = self.tool
        if min(q0[2], q1[2]) < self._table_z() + TABLE_CLEAR_MM:
            raise Breakage(f"T{tool.number} into the table at z {min(q0[2], q1[2]):.3f}")
        if self._mesh_top is None:
            self._mesh_top = float(np.max(self.workpiece.vertices()[:, 2]))
        if min(q0[2], q1[2]) > max(self._mesh_top, hm.highest()) + 1e-6:
            return   # above everything: nothing to cut
        removed, depth = hm.carve(q0, q1, tool.radius_mm, tool.kind == "ball")
        if removed <= 1e-9:
            return
        if not turning:
            raise Breakage(f"T{tool.number} cut {removed:.3f} mm3 with the spindle stopped")
        if rpm > tool.max_rpm:
            raise Breakage(f"T{tool.number} at S{rpm:.0f}, above its {tool.max_rpm:.0f} rpm")
        if depth > tool.flute_length_mm:
            raise Breakage(f"T{tool.number} cut {depth:.3f} mm deep, beyond its {tool.flute_length_mm:g} mm flutes")
        if self._move.get("seq") != b.seq:
            self._flush()
            self._move = {"seq": b.seq, "removed": 0.0, "depth": 0.0}
            self._row = {"seq": b.seq, "line": b.line, "tool": tool.number,
                         "from": [round(float(v), 4) for v in q0]}
        m = self._move
        m["removed"] += removed
        m["depth"] = max(m["depth"], depth)
        self._row["to"] = [round(float(v), 4) for v in q1]
        self.removed_mm3 += removed

    def finished(self, b: Block, t: float) -> None:
        if self._move.get("seq") == b.seq:
            self._row["t"] = round(t, 4)
            self._flush()

    def _flush(self) -> None:
        m = self._move
        if m and self._log is not None:
            row = dict(self._row, removed_mm3=round(m["removed"], 4), depth_mm=round(m["depth"], 4))
            self._log.write(json.dumps(row) + "\n")
            self._log.flush()
        self._move = {}

    def setter_hit(self, p0: Pos5, p1: Pos5) -> float | None:
        """Where (fraction of p0→p1) the tool's tip meets the tool setter's top, or None."""
        sx, sy, sz = self.setter
        a, b = self.tip(p0), self.tip(p1)
        if a[2] < sz or b[2] >= sz or abs(a[2] - b[2]) < 1e-12:
            return None
        f = (a[2] - sz) / (a[2] - b[2])
        x, y = a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])
        return f if (x - sx) ** 2 + (y - sy) ** 2 <= 25.0 else None

    def close(self) -> None:
        self._flush()
        if self._log is not None:
            self._log.close()
            self._log = None


def use_deposit_map(ctx: SimContext, wp: Workpiece) -> None:
    """Metal the CNC deposits is the World's height map in the workpiece frame (its substrate the
    workpiece mesh): the touch probe reads it, so probing after a repair sees the deposit."""
    phys = attach(ctx)
    if phys is None:
        return
    phys.set_substrate("cnc", wp.top_z)
    wp.deposit_map = phys.height_map("cnc")
    wp.settle = ctx.world.settle if ctx.world is not None else None   # a touch sees every bead laid before it
