"""The build record written in a worker process, off the controller's interpreter.

Plotting holds the interpreter lock for tens of milliseconds at a time; on a worker thread of
the controller it delayed the 10 ms device cycles by up to 100 ms (measured: the loop thread
waiting for the lock while the plotting thread, time-shared, waited for a CPU beside a busy
process), enough to lose the cell I/O link or trip the power source's watchdog right after a
build. One worker process per controller process, started on first use from a fork server that
has the report modules imported already, reads the journal on its own connection (WAL lets it
read while the controller's connection stays open).
"""
from __future__ import annotations

import asyncio
import atexit
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

_POOL: ProcessPoolExecutor | None = None


def _pool() -> ProcessPoolExecutor:
    global _POOL
    if _POOL is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["controller.report.summary", "controller.journal.store"])
        _POOL = ProcessPoolExecutor(max_workers=1, mp_context=ctx)
        atexit.register(_POOL.shutdown, wait=False, cancel_futures=True)
    return _POOL


def _write(run_dir: str, job: dict[str, Any] | None, plots: bool, state: str | None) -> str:
    """In the worker: open the run's journal and write the record; the path of report.json."""
    from controller.journal.store import Journal
    from controller.report.summary import write_report

    journal = Journal(Path(run_dir) / "journal.sqlite")
    try:
        return str(write_report(journal, run_dir, job, plots=plots, state=state))
    finally:
        journal.close()


async def write_report_elsewhere(run_dir: Path, job: dict[str, Any] | None, plots: bool = True,
                                 state: str | None = None) -> Path:
    """Write report.json (+ CSV, PNGs) for `run_dir` in the worker process; await its path."""
    # The first submit starts the fork server and waits for its imports (seconds): on a thread.
    fut = await asyncio.to_thread(lambda: _pool().submit(_write, str(run_dir), job, plots, state))
    path: str = await asyncio.wrap_future(fut)
    return Path(path)

