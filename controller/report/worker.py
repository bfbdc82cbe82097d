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
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from core.errors import CellError
import argparse

if TYPE_CHECKING:  # annotations only: the controller has them loaded already
    from controller.job.model import CellJob
    from core.config import CellConfig

TIMEOUT_S = 300.0   # a record that takes longer is abandoned (the journal keeps everything)
# CELL_RECORD_PLOTS=0 leaves the PNGs out of the build-end record (report.json and beads.csv are
# written all the same; `cell report RUN_DIR` draws them later from the journal). Drawing them is
# about 1.5 s of a 2 s record: a cell that runs many short builds, or the test suite, may skip it.
PLOTS_ENV = "CELL_RECORD_PLOTS"


@dataclass(frozen=True)
class RecordsTarget:
    """The shop's record store the build-end record is sent to (cell.yaml `records.url`, docs/records.md)."""

    url: str
    runs_dir: Path       # the cell's runs directory: its queued records are sent after every build
    cell: str
    timeout_s: float


def records_target(cfg: CellConfig, runs_dir: Path) -> RecordsTarget | None:
    r = cfg.records
    return RecordsTarget(r.url, Path(runs_dir), cfg.cell.name, r.connect_timeout_s) if r.url else None


def build_end_plots() -> bool:
    """Whether the build-end record draws its plots: yes, unless CELL_RECORD_PLOTS is 0/no/off/false."""
    return os.environ.get(PLOTS_ENV, "1").strip().lower() not in ("0", "no", "off", "false")


def write_record(run_dir: str | Path, job: CellJob | None, plots: bool = True,
                 state: str | None = None, timeout_s: float = TIMEOUT_S,
                 records: RecordsTarget | None = None) -> Path:
    """Write report.json (+ beads.csv, PNGs) for `run_dir` in a child process; its path. With
    `records`, the child then sends it to the store (queued in the run directory if it cannot).

    Blocking: call it on a thread (`write_report_elsewhere`). A CellError names the run
    directory and the child's last error line when the record could not be written."""
    return _write(run_dir, job, plots, state, timeout_s, records)[0]


def _write(run_dir: str | Path, job: CellJob | None, plots: bool, state: str | None, timeout_s: float,
           records: RecordsTarget | None) -> tuple[Path, dict[str, Any] | None]:
    run_dir = Path(run_dir)
    cmd = [sys.executable, "-m", "controller.report.worker", str(run_dir)]
    if state:
        cmd += ["--state", state]
    if not plots:
        cmd.append("--no-plots")
    env = dict(os.environ)
    if records is not None:   # the URL in the environment, not on a command line `ps` shows
        # lazy: the records room loads only for a cell with a store
        from controller.records.queue import URL_ENV, mark_pending

        mark_pending(run_dir, "build ended: being sent")   # never lost: queued until the store has it
        env[URL_ENV] = records.url
        cmd += ["--runs", str(records.runs_dir), "--cell", records.cell, "--records-timeout", str(records.timeout_s)]
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
    sent = next((json.loads(x[len(_RECORDS):]) for x in out if x.startswith(_RECORDS)), None)
    return Path(out[-1]), sent


_RECORDS = "records: "   # the child's line saying what the store got


async def write_report_elsewhere(run_dir: Path, job: CellJob | None, plots: bool = True,
                                 state: str | None = None) -> Path:
    """Write report.json (+ CSV, PNGs) for `run_dir` in a child process; await its path."""
    return await asyncio.to_thread(write_record, run_dir, job, plots, state)


def _sent_text(run_dir: Path, sent: dict[str, Any] | None) -> str:
    """What the store got, for the message line ('' without a store)."""
    if sent is None:
        return ""
    if run_dir.as_posix() in sent.get("queued_dirs", []) or str(run_dir) in sent.get("queued_dirs", []):
        why = (sent.get("errors") or ["?"])[0]
        return f"; queued for the record store ({why}): `cell records sync` sends it"
    more = sent["sent"] + sent["unchanged"] - 1
    return "; sent to the record store" + (f" (and {more} queued before)" if more > 0 else "")


async def record_build_end(journal: Any, bus: Any, run_dir: Path, job: CellJob | None,
                           state: str | None, records: RecordsTarget | None = None) -> Path | None:
    """The one record writer at the end of every build (controller/api/ `start()`): the record
    in the run directory, its path journaled and on the views' message line. A record that could
    not be written never turns the build's end into an error: the reason is journaled and shown,
    and `cell report RUN_DIR` writes it later from the journal."""
    plots = build_end_plots()
    try:
        path: Path | None
        path, sent = await asyncio.to_thread(_write, run_dir, job, plots, state, TIMEOUT_S, records)
        drawn = "plots" if plots else f"no plots ({PLOTS_ENV}=0): `cell report {run_dir}` draws them"
        msg = f"{state or 'build'}: record in {run_dir} (report.json, beads.csv, {drawn}){_sent_text(run_dir, sent)}"
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
    ap.add_argument("--runs", default=None)
    ap.add_argument("--cell", default="unknown")
    ap.add_argument("--records-timeout", type=float, default=5.0)
    args = ap.parse_args(argv)
    text = sys.stdin.read()
    # lazy: the report modules (matplotlib) load only when a record is written
    from controller.job.read import job_from_dict
    from controller.report.run import write_run_report

    job = job_from_dict(json.loads(text), "the build's job") if text.strip() else None
    path = write_run_report(args.run_dir, job, plots=not args.no_plots, state=args.state)
    url = os.environ.get("CELL_RECORDS_URL")
    if url:
        # lazy: the records room (and its database driver) loads only for a cell with a store
        from controller.records.queue import after_build

        res = after_build(Path(args.run_dir), Path(args.runs) if args.runs else None, url, cell=args.cell,
                          timeout_s=args.records_timeout)
        print(_RECORDS + json.dumps(res.as_dict()))
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
