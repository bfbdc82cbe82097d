"""The build record written in a child process, off the controller's interpreter.

Plotting holds the interpreter lock for tens of milliseconds at a time; on a worker thread of
the controller it delayed the 10 ms device cycles by up to 100 ms (measured: the loop thread
waiting for the lock while the plotting thread, time-shared, waited for a CPU beside a busy
process), enough to lose the cell I/O link or trip the power source's watchdog right after a
build. The child (`python -m controller.report.worker RUN_DIR`) reads the journal on its own
connection (WAL lets it read while the controller's connection stays open) and the job's
canonical JSON from its stdin (the journal's copy when none is given), read typed there as a file
is (controller/job/read.py).

A plain child process, not a multiprocessing pool: a forkserver pool re-imports the parent's
`__main__`, which failed (and would have run the caller's script a second time) whenever the
controller was embedded in a script without a `__main__` guard, and its atexit shutdown cancelled
a record still being written when the TUI quit. The child is independent of how the controller
was started. It inherits no real-time priority (the controller's threads ask for
SCHED_RESET_ON_FORK), so the device cycles (SCHED_FIFO) come first; it is not niced either: on a
loaded host (load 11 on 2 cores) a nice-10 child got so little CPU that the TUI's record took
more than 150 s.
"""
from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from core.errors import CellError
import argparse

if TYPE_CHECKING:  # the typed job only annotates: the controller has it loaded already
    from controller.job.model import CellJob

TIMEOUT_S = 300.0   # a record that takes longer is abandoned (the journal keeps everything)
# CELL_RECORD_PLOTS=0 leaves the PNGs out of the build-end record (report.json and beads.csv are
# written all the same; `cell report RUN_DIR` draws them later from the journal). Drawing them is
# about 1.5 s of a 2 s record: a cell that runs many short builds, or the test suite, may skip it.
PLOTS_ENV = "CELL_RECORD_PLOTS"


def build_end_plots() -> bool:
    """Whether the build-end record draws its plots: yes, unless CELL_RECORD_PLOTS is 0/no/off/false."""
    return os.environ.get(PLOTS_ENV, "1").strip().lower() not in ("0", "no", "off", "false")


def write_record(run_dir: str | Path, job: CellJob | None, plots: bool = True,
                 state: str | None = None, timeout_s: float = TIMEOUT_S) -> Path:
    """Write report.json (+ beads.csv, PNGs) for `run_dir` in a child process; its path.

    Blocking: call it on a thread (`write_report_elsewhere`). A CellError names the run
    directory and the child's last error line when the record could not be written."""
    run_dir = Path(run_dir)
    cmd = [sys.executable, "-m", "controller.report.worker", str(run_dir)]
    if state:
        cmd += ["--state", state]
    if not plots:
        cmd.append("--no-plots")
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])   # this checkout, whatever the caller's cwd
    env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.setdefault("MPLBACKEND", "Agg")
    try:
        proc = subprocess.run(cmd, input=job.json if job is not None else "", capture_output=True,
                              text=True, env=env, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        raise CellError(f"build record of {run_dir}: not written within {timeout_s:.0f} s "
                        f"(`cell report {run_dir}` writes it from the journal)") from None
    except OSError as exc:
        raise CellError(f"build record of {run_dir}: cannot start the writer ({exc})") from None
    out = proc.stdout.strip().splitlines()
    if proc.returncode != 0 or not out:
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise CellError(f"build record of {run_dir}: the writer failed ({last}); "
                        f"`cell report {run_dir}` writes it from the journal")
    return Path(out[-1])


async def write_report_elsewhere(run_dir: Path, job: CellJob | None, plots: bool = True,
                                 state: str | None = None) -> Path:
    """Write report.json (+ CSV, PNGs) for `run_dir` in a child process; await its path."""
    return await asyncio.to_thread(write_record, run_dir, job, plots, state)


async def record_build_end(journal: Any, bus: Any, run_dir: Path, job: CellJob | None,
                           state: str | None) -> Path | None:
    """The one record writer at the end of every build (controller/api.py `start()`): the record
    in the run directory, its path journaled and on the views' message line. A record that could
    not be written never turns the build's end into an error: the reason is journaled and shown,
    and `cell report RUN_DIR` writes it later from the journal."""
    plots = build_end_plots()
    try:
        path: Path | None = await write_report_elsewhere(run_dir, job, plots=plots, state=state)
        drawn = "plots" if plots else f"no plots ({PLOTS_ENV}=0): `cell report {run_dir}` draws them"
        msg = f"{state or 'build'}: record in {run_dir} (report.json, beads.csv, {drawn})"
    except Exception as exc:   # noqa: BLE001  (whatever went wrong, the build's end stands)
        path, msg = None, f"{state or 'build'}: no record written: {exc}"
    try:
        journal.event("info", msg)
    except Exception:   # noqa: BLE001  (a journal that cannot be written is already a fault)
        pass
    bus.update(message=msg, record_path=str(path) if path else None)
    return path


def _main(argv: list[str]) -> int:
    """In the child: open the run's journal and write the record; print the path of report.json."""

    ap = argparse.ArgumentParser(prog="controller.report.worker")
    ap.add_argument("run_dir")
    ap.add_argument("--state", default=None)
    ap.add_argument("--no-plots", action="store_true")
    args = ap.parse_args(argv)
    text = sys.stdin.read()
    # lazy: the report modules (matplotlib) load only when a record is written
    from controller.job.read import job_from_dict
    from controller.report.run import write_run_report

    job = job_from_dict(json.loads(text), "the build's job") if text.strip() else None
    path = write_run_report(args.run_dir, job, plots=not args.no_plots, state=args.state)
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
