"""The physical coupling between simulators run in one process, as in the real cell.

The power-source simulator tells the world whether the arc is stable (and its current and
voltage); the motion simulators report every stretch of torch motion as they execute it.
Metal is deposited only where the torch moves while the arc is stable: the world records that
ground truth, one segment per uninterrupted stretch, to `deposit.jsonl` (docs/contract.md §6a), and
accumulates the heat input the cell-I/O simulator's thermal model draws on.

With process physics (`use_physics`, sims/process_world.py, docs/contract.md §6b) the world also knows
the part's shape: every deposited segment pours a bead into a height map, the torch's CTWD above
it is known at every moment (`stick_out_mm`, which the power-source simulator's current follows),
and each deposit row adds the truth: `ctwd_mm` (mean over the segment) and `bead_height_mm` (the
bead's rise on its centre line).

Times are simulated seconds (wall time × time scale), supplied by the callers.
"""
from __future__ import annotations

import json
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Callable, Iterator

if TYPE_CHECKING:
    from sims.process_world import ProcessPhysics

Vec3 = tuple[float, float, float]
PartSeg = tuple[Vec3, Vec3, Vec3]   # (from, to, tool axis) in the workpiece frame


@dataclass
class _Open:
    device: str
    move: object
    start: Vec3
    end: Vec3
    t0: float
    t1: float
    currents: list[float] = field(default_factory=list)
    part: PartSeg | None = None   # (from, to, axis) in the workpiece frame (CNC: from its true pose)
    voltages: list[float] = field(default_factory=list)
    wfs: list[float] = field(default_factory=list)
    ctwds: list[float] = field(default_factory=list)
    temp_c: float | None = None   # the part temperature when the segment closed (a deferred lay)


class World:
    """Shared state of the simulated cell. Thread-safe; cheap to call at every simulator tick."""

    def __init__(self, log_dir: str | Path | None = None, arc_efficiency: float = 0.8,
                 defer_lays: bool = False) -> None:
        self._lock = threading.Lock()
        # Laying a segment's bead costs 1-2.5 ms; at time scale 60 a short move lasts 0.3 ms, so
        # laid at once the beads held the simulators' loop (the robot's EXEs, the power source's
        # and the cell I/O's replies) for tens of ms. With `defer_lays` a closed segment waits in
        # `_pending` and the simulators' executors lay it in their spare time (`settle`); it is
        # laid before anything reads the shape it changes: a new bead (its "before" surface), a
        # probe touch (`Workpiece.settle`), `segments`, `flush`, `close`. The CTWD under the torch
        # reads the surface before the current bead, which the current bead's own pending
        # segments do not change, plus the bead's settled rise (laid up to a few segments ago).
        self.defer_lays = defer_lays
        self._pending: deque[tuple[_Open, dict[str, Any]] | None] = deque()   # None: a bead's end
        self._laying: Iterator[None] | None = None   # the segment being laid, 10 mm at a time
        self.arc_stable = False
        self.current_a = 0.0
        self.voltage_v = 0.0
        self.wfs_m_min = 0.0
        self.physics: ProcessPhysics | None = None
        self.arc_efficiency = arc_efficiency
        self.heat_j = 0.0  # total heat put into the part: η·U·I integrated over arc time
        self._heat_t: float | None = None
        self._segments: list[dict[str, Any]] = []
        self._open: _Open | None = None
        self._listeners: list[Callable[[dict[str, Any]], None]] = []
        self._fh: IO[str] | None = None
        if log_dir is not None:
            Path(log_dir).mkdir(parents=True, exist_ok=True)
            self._fh = open(Path(log_dir) / "deposit.jsonl", "a", encoding="utf-8")

    def use_physics(self, physics: ProcessPhysics) -> None:
        """Give the world its process physics (height maps, CTWD, melting rate)."""
        with self._lock:
            self.physics = physics

    # -- power source side ----------------------------------------------------------------
    def set_arc(self, stable: bool, current_a: float, voltage_v: float, t: float,
                wfs_m_min: float | None = None) -> None:
        """Called by the power-source simulator whenever the arc state or actuals change."""
        with self._lock:
            self._integrate_heat(t)
            if stable != self.arc_stable and self._open is not None:
                self._flush()
            if not stable and self.arc_stable and self.physics is not None:
                self._end_bead()
            if stable and not self.arc_stable and self.physics is not None:
                self._settle(None)   # the previous bead's metal, before the new bead's "before"
                self.physics.new_bead()
            self.arc_stable = stable
            self.current_a = current_a if stable else 0.0
            self.voltage_v = voltage_v if stable else 0.0
            self.wfs_m_min = (wfs_m_min or 0.0) if stable else 0.0

    def stick_out_mm(self) -> float | None:
        """The torch's CTWD now (the power source's current follows it); None without physics or motion."""
        with self._lock:
            return self.physics.ctwd_mm() if self.physics is not None else None

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
                    part: PartSeg | None = None) -> None:
        """A motion simulator moved the torch from p0 (at t0) to p1 (at t1) within one move.

        `move` identifies the move being executed (e.g. its sequence number); a stretch of
        several calls for the same move while the arc stays stable becomes one segment.
        `part`: (from, to, tool axis) of this stretch in the workpiece frame, when the simulator knows it.
        """
        with self._lock:
            self._integrate_heat(t1)
            if self.physics is not None:
                self._torch(device, p0, p1, part)
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
            o.wfs.append(self.wfs_m_min)
            if self.physics is not None:
                c = self.physics.ctwd_mm()
                if c is not None:
                    o.ctwds.append(c)

    def _torch(self, device: str, p0: Vec3, p1: Vec3, part: PartSeg | None) -> None:
        assert self.physics is not None
        a, b, axis = (part[0], part[1], part[2]) if part is not None else (p0, p1, (0.0, 0.0, 1.0))
        d = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
        self.physics.torch_at(device, (float(b[0]), float(b[1]), float(b[2])),
                              (float(axis[0]), float(axis[1]), float(axis[2])), d)

    def motion_stopped(self, device: str) -> None:
        """The device finished a move or stopped (hold, abort): close the open segment."""
        with self._lock:
            if self._open is not None and self._open.device == device:
                self._flush()

    @property
    def segments(self) -> list[dict[str, Any]]:
        """Every deposited segment so far (each one laid)."""
        self.settle()
        return self._segments

    def settle(self, deadline: float | None = None) -> bool:
        """Lay pending segments (all, or until `time.perf_counter()` passes `deadline`);
        True when none is left."""
        if not self._pending and self._laying is None:   # the usual case: no lock (a thread
            return True                                     # holding it may wait for the GIL)
        with self._lock:
            return self._settle(deadline)

    def _settle(self, deadline: float | None) -> bool:
        # A deferred bead is poured 10 mm at a time (HeightMap.lay_steps), the deadline checked in
        # between: a whole 80 mm segment held the simulators' loop for 10-17 ms (30+ ms beside a CPU
        # hog, the power source's and the cell I/O's replies waiting). Same cells, same order: same bead.
        while self._laying is not None or self._pending:
            if deadline is not None and time.perf_counter() > deadline:
                return False
            if self._laying is None:
                item = self._pending.popleft()
                if item is None:
                    assert self.physics is not None
                    self.physics.end_bead()
                    continue
                self._laying = self._record_steps(*item)
            if next(self._laying, _DONE) is _DONE:
                self._laying = None
        return True

    def flush(self) -> None:
        with self._lock:
            if self._open is not None:
                self._flush()
            self._settle(None)
            if self._fh is not None:
                self._fh.flush()

    def close(self) -> None:
        self.flush()
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def subscribe(self, fn: Callable[[dict[str, Any]], None]) -> None:
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
        if o.wfs:   # the wire feed the source ran (its synergic current: what the segment was commanded)
            seg["wfs_m_min"] = round(sum(o.wfs) / len(o.wfs), 3)
        if o.part is not None:
            seg["part"] = {"from": [round(float(v), 4) for v in o.part[0]], "to": [round(float(v), 4) for v in o.part[1]]}
            seg["axis"] = [round(float(v), 5) for v in o.part[2]]
        if self.defer_lays and self.physics is not None:
            o.temp_c = self.physics.part_temperature_c()   # the part's temperature now, not at laying
            self._pending.append((o, seg))
        else:
            self._record(o, seg)

    def _end_bead(self) -> None:
        """The arc went out: the bead's open end sags (after its last segment is laid)."""
        assert self.physics is not None
        if self.defer_lays:
            self._pending.append(None)
        else:
            self.physics.end_bead()

    def _record(self, o: _Open, seg: dict[str, Any]) -> None:
        """Lay a closed segment's bead and log it."""
        for _ in self._record_steps(o, seg):
            pass

    def _record_steps(self, o: _Open, seg: dict[str, Any]) -> Iterator[None]:
        """`_record`, a yield after every 10 mm of the bead poured."""
        if self.physics is not None:
            yield from self._lay(o, seg)
        self._segments.append(seg)
        if self._fh is not None:
            self._fh.write(json.dumps(seg) + "\n")
            self._fh.flush()
        for fn in self._listeners:
            fn(seg)


    def _lay(self, o: _Open, seg: dict[str, Any]) -> Iterator[None]:
        """The bead of a deposited segment into the height map, 10 mm at a time (a yield in
        between); its truth into the row."""
        assert self.physics is not None
        q0, q1 = (o.part[0], o.part[1]) if o.part is not None else (o.start, o.end)
        wfs = sum(o.wfs) / len(o.wfs) if o.wfs else 0.0
        laid = yield from self.physics.lay_steps(o.device, q0, q1, o.t1 - o.t0, seg["current_a"], wfs, o.temp_c)
        if o.ctwds:
            seg["ctwd_mm"] = round(sum(o.ctwds) / len(o.ctwds), 3)
        if laid is not None:
            seg["bead_height_mm"] = round(self.physics.rise_mm(o.device), 4)


_DONE = object()


def _dist(a: Vec3, b: Vec3) -> float:
    return float(sum((x - y) ** 2 for x, y in zip(a, b)) ** 0.5)
