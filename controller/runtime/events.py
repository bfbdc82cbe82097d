"""Immutable snapshots of the cell for the operator's views (TUI, progress lines) and a bus.

The controller publishes a new `Snapshot` whenever something a user would see changes (state,
progress, live process values, link statistics, alarms, interpass countdown). Views never
reach into the controller: they subscribe and render the snapshot they are given.
"""
from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass, field, replace
from typing import AsyncIterator, Callable, TypedDict, Unpack


@dataclass(frozen=True)
class Alarm:
    t: float                        # wall time (time.time())
    kind: str                       # fault, estop, warning
    message: str
    layer: int | None = None
    pass_: int | None = None
    position: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class LinkStat:
    device: str                     # robot, cnc, power_source, cellio
    url: str
    connected: bool = False
    frames_tx: int = 0
    frames_rx: int = 0
    errors: int = 0                 # late + bad (kept for the views that show one number)
    queue_free: int | None = None   # robot queue slots free, CNC rx buffer bytes free
    late: int = 0                   # valid replies after their cycle (robot: resends, timeouts)
    lost: int = 0                   # link losses
    bad: int = 0                    # invalid frames (CRC, NAK, garbage)
    max_period_ms: float | None = None  # cyclic devices: the longest time between two cycles
    p99_period_ms: float | None = None  # cyclic devices: the 99th percentile of that time
    # cyclic devices: the longest period the controller is to blame for, and the OS's share (run
    # queue, a stopped CPU) and the in-process simulators' share (they held the GIL) of that
    # period's lateness: docs/testing.md, "A loop that never blocks"
    max_own_period_ms: float | None = None
    os_delay_ms: float | None = None
    device_delay_ms: float | None = None


@dataclass(frozen=True)
class Snapshot:
    """What the operator sees at one moment. All fields are plain values; safe to share."""

    t: float = 0.0
    state: str = "disconnected"
    job_name: str | None = None
    run_dir: str | None = None
    layers_total: int = 0
    passes_total: int = 0
    layer: int | None = None        # the layer being built (0-based index), None outside a build
    pass_: int | None = None        # the pass within the layer
    passes_in_layer: int = 0
    layers_done: int = 0
    passes_done: int = 0
    arc_starts: int = 0
    current_a: float | None = None
    voltage_v: float | None = None
    wfs_m_min: float | None = None
    arc_on: bool | None = None      # the power source's arc-stable bit (None: not read)
    travel_speed_mm_min: float | None = None   # the bead's speed while depositing
    job_hash: str | None = None
    temperature_c: float | None = None
    interpass_limit_c: float | None = None
    interpass_remaining_s: float | None = None   # dwell countdown when no pyrometer reading
    position: tuple[float, float, float] | None = None
    links: tuple[LinkStat, ...] = ()
    alarms: tuple[Alarm, ...] = ()
    allowed_commands: tuple[str, ...] = ()
    message: str = ""                # the latest progress line
    stick_out_mm: float | None = None           # the latest stick-out (CTWD) estimate (docs/closed-loop.md)
    layer_height_error_mm: float | None = None  # the last layer's measured top − its planned top
    z_correction_mm: float | None = None        # z offset the current layer is laid with
    path_rms_mm: float | None = None            # the path loop: last layer's RMS height error along the path
    path_spread_mm: float | None = None         # ... its top's spread (max − min) along the path
    path_factor_min: float | None = None        # the current layer's smallest per-segment speed factor
    path_factor_max: float | None = None        # ... and largest
    record_path: str | None = None   # the build record (report.json) of the last build that ended
    wire_lot: str | None = None      # the running build's trace (docs/records.md)
    gas: str | None = None
    operator: str | None = None

    @property
    def progress(self) -> float:
        """Fraction of passes done, 0..1."""
        return self.passes_done / self.passes_total if self.passes_total else 0.0

    def with_(self, **changes: Unpack[SnapshotChanges]) -> "Snapshot":
        return replace(self, t=time.time(), **changes)


class SnapshotChanges(TypedDict, total=False):
    """The fields of `Snapshot` an update may change (all but `t`, which the update stamps)."""

    state: str
    job_name: str | None
    run_dir: str | None
    layers_total: int
    passes_total: int
    layer: int | None
    pass_: int | None
    passes_in_layer: int
    layers_done: int
    passes_done: int
    arc_starts: int
    current_a: float | None
    voltage_v: float | None
    wfs_m_min: float | None
    arc_on: bool | None
    travel_speed_mm_min: float | None
    job_hash: str | None
    temperature_c: float | None
    interpass_limit_c: float | None
    interpass_remaining_s: float | None
    position: tuple[float, float, float] | None
    links: tuple[LinkStat, ...]
    alarms: tuple[Alarm, ...]
    allowed_commands: tuple[str, ...]
    message: str
    record_path: str | None
    wire_lot: str | None
    gas: str | None
    operator: str | None
    stick_out_mm: float | None
    layer_height_error_mm: float | None
    z_correction_mm: float | None
    path_rms_mm: float | None
    path_spread_mm: float | None
    path_factor_min: float | None
    path_factor_max: float | None


class AlarmWhere(TypedDict, total=False):
    """Where an alarm was raised (the optional fields of `Alarm`)."""

    layer: int | None
    pass_: int | None
    position: tuple[float, float, float] | None


Subscriber = Callable[[Snapshot], None]


class EventBus:
    """Holds the latest snapshot; calls subscribers on every change (from any thread).

    `subscribe(fn)` calls `fn` at once with the current snapshot, then on every update, in the
    publishing thread: a view on another loop should hand it over (e.g. `call_soon_threadsafe`).
    `updates()` is an async iterator on the caller's loop that yields the latest snapshot,
    skipping intermediate ones when the reader is slower than the publisher.
    """

    def __init__(self, initial: Snapshot | None = None) -> None:
        self._snap = initial or Snapshot(t=time.time())
        self._subs: list[Subscriber] = []
        self._lock = threading.Lock()

    @property
    def latest(self) -> Snapshot:
        return self._snap

    def update(self, **changes: Unpack[SnapshotChanges]) -> Snapshot:
        with self._lock:
            self._snap = self._snap.with_(**changes)
            snap, subs = self._snap, list(self._subs)
        return self._notify(snap, subs)

    def publish(self, snap: Snapshot) -> Snapshot:
        """Replace the snapshot whole (a copy of another process's bus) and notify."""
        with self._lock:
            self._snap = snap
            subs = list(self._subs)
        return self._notify(snap, subs)

    @staticmethod
    def _notify(snap: Snapshot, subs: list[Subscriber]) -> Snapshot:
        for fn in subs:
            try:
                fn(snap)
            except Exception:  # a broken view must not stop the controller
                pass
        return snap

    def alarm(self, kind: str, message: str, **where: Unpack[AlarmWhere]) -> Snapshot:
        a = Alarm(t=time.time(), kind=kind, message=message, **where)
        return self.update(alarms=self._snap.alarms + (a,))

    def subscribe(self, fn: Subscriber) -> Callable[[], None]:
        with self._lock:
            self._subs.append(fn)
        fn(self._snap)

        def unsubscribe() -> None:
            with self._lock:
                if fn in self._subs:
                    self._subs.remove(fn)

        return unsubscribe

    async def updates(self) -> AsyncIterator[Snapshot]:
        """Async iterator of snapshots on the running loop (latest wins)."""
        loop = asyncio.get_running_loop()
        changed = asyncio.Event()

        def wake(_s: Snapshot) -> None:
            loop.call_soon_threadsafe(changed.set)

        unsubscribe = self.subscribe(wake)
        try:
            while True:
                await changed.wait()
                changed.clear()
                yield self._snap
        finally:
            unsubscribe()


@dataclass
class ProgressPrinter:
    """Prints a progress line when the layer changes or an alarm is raised (for `cell run`)."""

    write: Callable[[str], None]
    _layer: int | None = None
    _alarms: int = 0
    _state: str = ""
    last_lines: list[str] = field(default_factory=list)

    def __call__(self, s: Snapshot) -> None:
        lines = []
        if s.state != self._state and s.state in ("fault", "estop", "complete", "aborted", "paused"):
            lines.append(f"state {s.state}")
        self._state = s.state
        if s.layer is not None and s.layer != self._layer:
            self._layer = s.layer
            temp = f", part {s.temperature_c:.0f} °C" if s.temperature_c is not None else ""
            lines.append(f"layer {s.layer + 1}/{s.layers_total}: {s.passes_done}/{s.passes_total} passes done{temp}")
        for a in s.alarms[self._alarms:]:
            where = f" (layer {a.layer}, pass {a.pass_}: job indices)" if a.layer is not None and a.pass_ is not None else ""
            lines.append(f"{a.kind}: {a.message}{where}")
        self._alarms = len(s.alarms)
        for line in lines:
            self.write(line)
