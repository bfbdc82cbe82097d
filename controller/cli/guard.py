"""The guard of every command that moves a device: the cell's lock and the stop signals.

`with guarded(cfg, config_path):` takes the cell's lock (controller/runtime/cell_lock.py: a
second controller is refused with exit 2 before any device is opened) and holds SIGINT, SIGTERM
and SIGHUP for the command (controller/runtime/stops.py). Inside the asyncio loop, `attach(ctl)`
turns the first signal into the controller's fault path (`CellController.stop_now`: weld start
dropped, motion held, journaled) or, before a build runs, into cancelling the command's task
(its `finally` releases the devices: the CNC's safe stop, the robot's hold); `detach()` goes back
to recording. `exit_code(state)` is 130 / 143 / 129 when a signal stopped a build that did not
complete, else None.
"""
from __future__ import annotations

import asyncio
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from controller.cli import outcome
from controller.api import signals as stops_mod
from controller.api.lock import acquire
from controller.api.signals import SignalStop, StopSignals
from core.config import load_cell
from core.errors import CellError


def current() -> StopSignals | None:
    """The StopSignals of the command running in this process (None outside `guarded`)."""
    return stops_mod.current()


@contextmanager
def guarded(cfg: Any, config_path: str | Path | None, *, lock: bool = True) -> Iterator[StopSignals]:
    """The cell's lock (unless `lock` is False) and the stop signals for the command's life."""
    held = acquire(cfg.cell.name, config_path) if lock else None
    try:
        with StopSignals() as stops, stops_mod.installed(stops):
            yield stops
    finally:
        if held is not None:
            held.release()


attach = stops_mod.attach
detach = stops_mod.detach


def exit_code(state: str | None) -> int | None:
    """128 + the signal number when a signal stopped the command short of `complete`."""
    stops = stops_mod.current()
    if stops is None or stops.received is None or state == "complete":
        return None
    return stops.exit_code()


def _err(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()
    outcome.error(line)


def command(fn: Callable[[Any], int]) -> Callable[[Any], int]:
    """A CLI handler run under `guarded` (the cell of `--cell-config`, default cell.yaml): a
    second controller is refused (exit 2); a signal that stopped it exits 130 / 143 / 129 with
    one `error:` line when no state line was printed."""
    def run(args: Any) -> int:
        path = getattr(args, "cell_config", None)
        with guarded(load_cell(path), path) as stops:
            try:
                return fn(args)
            except (asyncio.CancelledError, SignalStop, KeyboardInterrupt):
                if stops.received is None:
                    raise
                _err(f"error: stopped by {stops.name} before the build ran: every device opened was "
                     "stopped safely and released; nothing was deposited")
                return stops.exit_code() or 1
            except CellError as exc:
                if stops.received is None:
                    raise
                _err(f"error: stopped by {stops.name}: {exc}")
                return stops.exit_code() or 1

    run.__doc__ = fn.__doc__
    return run


async def run_attached(coro: Any, say: Callable[[str], None] | None = None) -> Any:
    """Await `coro` with the signals attached (no controller: a signal cancels it; its own
    `finally` / `except` blocks stop the devices safely, e.g. the CNC in align's run_on_url)."""
    attach(None, say)
    try:
        return await coro
    finally:
        detach()
