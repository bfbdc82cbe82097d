"""Every stop is safe (docs/contract.md §6): SIGINT, SIGTERM and SIGHUP take the fault path.

`StopSignals` is held for the life of a command that moves a device (`cell run`, `cell resume`,
`cell align run`, `cell repair run`, `cell demo`, a TUI build):

- outside the asyncio loop (argument checks, the lock, closing the simulators) a signal is
  only recorded: nothing moves yet, or everything has already stopped;
- inside the loop (`attach(on_stop)`, registered with `loop.add_signal_handler`) the first
  signal calls `on_stop(reason)` on the loop's thread: the controller trips its interlocks with
  it (weld start dropped in the next bus cycle, motion held: robot `!HOLD`; CNC
  `CncLink.safe_stop`), exactly as a lost link does, and the cause is journaled;
- a signal received before the loop attached makes `attach` raise `SignalStop` before any
  device is opened;
- a second signal (any of the three) never skips the safe stop: it is noted (`on_note`, the
  journal) and not obeyed.

The command's exit code is `exit_code()`: 128 + the signal number (130 SIGINT, 143 SIGTERM,
129 SIGHUP) when a signal stopped it, else None (the command's own 0 / 1 / 2 / 3).
"""
from __future__ import annotations

import asyncio
import signal
import sys
import time
from contextlib import contextmanager
from types import FrameType
from typing import Any, Callable, Iterator, Protocol

from controller.journal.store import Journal
from core.errors import CellError

SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
EXIT_FOR_SIGNAL = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGHUP: 129}


class SignalStop(CellError):
    """The command was stopped by a signal before it reached a device (nothing moved)."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name} before any device was opened")


def reason_for(signum: int) -> str:
    """The fault message of a signal: what the journal and the alarm line say."""
    name = signal.Signals(signum).name
    why = {"SIGINT": "Ctrl-C", "SIGTERM": "terminated", "SIGHUP": "terminal closed"}.get(name, "signal")
    return f"stopped by {name} ({why}): weld start dropped, motion held"


class StopSignals:
    """SIGINT / SIGTERM / SIGHUP for one command (a context manager, main thread only)."""

    def __init__(self) -> None:
        self.received: int | None = None          # the first signal's number
        self.t_received: float | None = None      # time.monotonic() of the first signal
        self.count = 0
        self.notes: list[str] = []
        self._on_stop: Callable[[str], None] | None = None
        self._on_note: Callable[[str], None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._prev: dict[signal.Signals, Any] = {}

    # -- the command's life -------------------------------------------------------------------
    def __enter__(self) -> "StopSignals":
        for sig in SIGNALS:
            self._prev[sig] = signal.signal(sig, self._recorded)
        return self

    def __exit__(self, *exc: object) -> None:
        self.detach()
        for sig, prev in self._prev.items():
            try:
                signal.signal(sig, prev)
            except (ValueError, TypeError):
                pass
        self._prev.clear()

    def _recorded(self, signum: int, _frame: FrameType | None) -> None:
        self._got(signum)

    # -- inside the loop ------------------------------------------------------------------------
    def attach(self, on_stop: Callable[[str], None], on_note: Callable[[str], None] | None = None) -> None:
        """Take the signals on the running loop: the first calls `on_stop(reason)`, later ones
        `on_note(text)`. Raises SignalStop when a signal already came (no device opened yet)."""
        if self.received is not None:
            raise SignalStop(self.received)
        loop = asyncio.get_running_loop()
        self._loop, self._on_stop, self._on_note = loop, on_stop, on_note
        for sig in SIGNALS:
            loop.add_signal_handler(sig, self._got, int(sig))

    def forward(self, on_stop: Callable[[str], None], on_note: Callable[[str], None] | None = None) -> None:
        """Without a loop of ours on this thread (the TUI: Textual owns the main thread's loop, the
        controller runs on a thread): the Python-level handlers call `on_stop(reason)` themselves;
        it must hand the stop to the controller's loop (call_soon_threadsafe)."""
        self._on_stop, self._on_note = on_stop, on_note

    def detach(self) -> None:
        """Back to recording only (the loop's handlers removed; asyncio would restore SIG_DFL)."""
        loop, self._loop = self._loop, None
        self._on_stop = self._on_note = None
        if loop is None or loop.is_closed():
            return
        for sig in SIGNALS:
            try:
                loop.remove_signal_handler(sig)
            except (ValueError, RuntimeError):
                pass
            if self._prev:
                signal.signal(sig, self._recorded)

    def _got(self, signum: int) -> None:
        self.count += 1
        name = signal.Signals(signum).name
        if self.received is None:
            self.received, self.t_received = signum, time.monotonic()
            if self._on_stop is not None:
                self._on_stop(reason_for(signum))
            return
        note = (f"{name} received again during the safe stop after "
                f"{signal.Signals(self.received).name}: noted, not obeyed (the safe stop goes on)")
        self.notes.append(note)
        if self._on_note is not None:
            try:
                self._on_note(note)
            except Exception:
                pass

    # -- results --------------------------------------------------------------------------------
    @property
    def name(self) -> str | None:
        return signal.Signals(self.received).name if self.received is not None else None

    def exit_code(self) -> int | None:
        """128 + the signal number when a signal stopped the command, else None."""
        if self.received is None:
            return None
        return EXIT_FOR_SIGNAL.get(signal.Signals(self.received), 128 + self.received)


# -- the command's StopSignals, for the code inside its loop (CLI, TUI, repair chain) ---------------
_current: StopSignals | None = None


def current() -> StopSignals | None:
    """The StopSignals of the command running in this process (None when none is installed)."""
    return _current


@contextmanager
def installed(stops: StopSignals) -> Iterator[StopSignals]:
    """Make `stops` the command's StopSignals (what `attach` uses) while the block runs."""
    global _current
    prev, _current = _current, stops
    try:
        yield stops
    finally:
        _current = prev


class Stoppable(Protocol):
    """What a signal stops (controller.api.CellController): its build runner and journal, and the fault path."""

    @property
    def building(self) -> bool: ...
    @property
    def journal(self) -> Journal | None: ...
    def stop_now(self, reason: str) -> bool: ...


def attach(ctl: Stoppable | None = None, say: Callable[[str], None] | None = None) -> StopSignals | None:
    """On the running loop: the first signal stops `ctl` on the fault path (`ctl.stop_now`) or,
    before its build (no runner yet) or without a controller, cancels the current task (whose
    `finally` blocks stop and release the devices); a second one is noted in the journal and on
    stderr, not obeyed. Raises SignalStop if a signal came before the loop (nothing opened yet).
    Nothing happens when no StopSignals is installed (a library caller, a test)."""
    stops = _current
    if stops is None:
        return None
    task = asyncio.current_task()
    tell = say or _err

    def on_stop(reason: str) -> None:
        tell(f"{reason} (signal received; stopping safely)")
        building = ctl is not None and ctl.building
        stopped = ctl is not None and ctl.stop_now(reason)
        if not (stopped and building) and task is not None and not task.done():
            task.cancel()

    def on_note(note: str) -> None:
        tell(note)
        journal = ctl.journal if ctl is not None else None
        if journal is not None:
            try:
                journal.event("info", note)
            except Exception:
                pass

    stops.detach()
    stops.attach(on_stop, on_note)
    return stops


def detach() -> None:
    """Back to recording the signals only (the loop is about to end)."""
    if _current is not None:
        _current.detach()


def _err(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()
