"""The physical coupling between simulators run in one process, as in the real cell.

The power-source simulator tells the world whether the arc is stable (and its current and
voltage); the motion simulators report every stretch of torch motion as they execute it.
Metal is deposited only where the torch moves while the arc is stable: the world records that
ground truth, one segment per uninterrupted stretch, to `deposit.jsonl` (DESIGN.md §6a), and
accumulates the heat input the cell-I/O simulator's thermal model draws on.

Times are simulated seconds (wall time × time scale), supplied by the callers.
"""
from __future__ import annotations

import json
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Callable

Vec3 = tuple[float, float, float]


@dataclass
class _Open:
    device: str
    move: object
    start: Vec3
    end: Vec3
    t0: float
    t1: float
    currents: list[float] = field(default_factory=list)
    part: tuple | None = None   # (from, to, axis) in the workpiece frame (CNC: from its true pose)
    voltages: list[float] = field(default_factory=list)


class World:
    """Shared state of the simulated cell. Thread-safe; cheap to call at every simulator tick."""

    def __init__(self, log_dir: str | Path | None = None, arc_efficiency: float = 0.8) -> None:
        self._lock = threading.Lock()
        self.arc_stable = False
        self.current_a = 0.0
        self.voltage_v = 0.0
        self.arc_efficiency = arc_efficiency
        self.heat_j = 0.0  # total heat put into the part: η·U·I integrated over arc time
        self._heat_t: float | None = None
        self.segments: list[dict] = []
        self._open: _Open | None = None
        self._listeners: list[Callable[[dict], None]] = []
        self._fh: IO[str] | None = None
        if log_dir is not None:
            Path(log_dir).mkdir(parents=True, exist_ok=True)
            self._fh = open(Path(log_dir) / "deposit.jsonl", "a", encoding="utf-8")

    # -- power source side ----------------------------------------------------------------
    def set_arc(self, stable: bool, current_a: float, voltage_v: float, t: float) -> None:
        """Called by the power-source simulator whenever the arc state or actuals change."""
        with self._lock:
            self._integrate_heat(t)
            if stable != self.arc_stable and self._open is not None:
                self._flush()
            self.arc_stable = stable
            self.current_a = current_a if stable else 0.0
            self.voltage_v = voltage_v if stable else 0.0

    def _integrate_heat(self, t: float) -> None:
        if self._heat_t is not None and self.arc_stable and t > self._heat_t:
            self.heat_j += self.arc_efficiency * self.voltage_v * self.current_a * (t - self._heat_t)
        self._heat_t = t

    def heat_power_w(self) -> float:
        """Heat flowing into the part right now (η·U·I while the arc burns)."""
        with self._lock:
            return self.arc_efficiency * self.voltage_v * self.current_a if self.arc_stable else 0.0

    # -- motion side ------------------------------------------------------------------------
    def torch_moved(self, device: str, move: object, p0: Vec3, p1: Vec3, t0: float, t1: float,
                    part: tuple | None = None) -> None:
        """A motion simulator moved the torch from p0 (at t0) to p1 (at t1) within one move.

        `move` identifies the move being executed (e.g. its sequence number); a stretch of
        several calls for the same move while the arc stays stable becomes one segment.
        `part`: (from, to, tool axis) of this stretch in the workpiece frame, when the simulator knows it.
        """
        with self._lock:
            self._integrate_heat(t1)
            if not self.arc_stable:
                if self._open is not None:
                    self._flush()
                return
            o = self._open
            if o is not None and (o.device != device or o.move != move or _dist(o.end, p0) > 1e-6):
                self._flush()
                o = None
            if o is None:
                self._open = o = _Open(device, move, p0, p1, t0, t1)
                if part is not None:
                    o.part = part
            o.end, o.t1 = p1, t1
            if part is not None and o.part is not None:
                o.part = (o.part[0], part[1], part[2])
            o.currents.append(self.current_a)
            o.voltages.append(self.voltage_v)

    def motion_stopped(self, device: str) -> None:
        """The device finished a move or stopped (hold, abort): close the open segment."""
        with self._lock:
            if self._open is not None and self._open.device == device:
                self._flush()

    def flush(self) -> None:
        with self._lock:
            if self._open is not None:
                self._flush()
            if self._fh is not None:
                self._fh.flush()

    def close(self) -> None:
        self.flush()
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def subscribe(self, fn: Callable[[dict], None]) -> None:
        """Call `fn(segment)` for every deposited segment (used by tests and the TUI demo)."""
        self._listeners.append(fn)

    def _flush(self) -> None:
        o, self._open = self._open, None
        if o is None:
            return
        # on a rotary table the tip may stand still in the machine while it moves along the part
        if _dist(o.start, o.end) < 1e-9 and (o.part is None or _dist(o.part[0], o.part[1]) < 1e-9):
            return
        seg = {
            "from": [round(v, 4) for v in o.start],
            "to": [round(v, 4) for v in o.end],
            "t0": round(o.t0, 4),
            "t1": round(o.t1, 4),
            "current_a": round(sum(o.currents) / len(o.currents), 2),
            "voltage_v": round(sum(o.voltages) / len(o.voltages), 2),
            "device": o.device,
        }
        if o.part is not None:
            seg["part"] = {"from": [round(float(v), 4) for v in o.part[0]], "to": [round(float(v), 4) for v in o.part[1]]}
            seg["axis"] = [round(float(v), 5) for v in o.part[2]]
        self.segments.append(seg)
        if self._fh is not None:
            self._fh.write(json.dumps(seg) + "\n")
            self._fh.flush()
        for fn in self._listeners:
            fn(seg)


def _dist(a: Vec3, b: Vec3) -> float:
    return sum((x - y) ** 2 for x, y in zip(a, b)) ** 0.5
