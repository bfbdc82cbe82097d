"""What the operator's terminal UI needs from the controller, and nothing more: a thread-and-view
adapter over the API (controller/api/).

The TUI (controller/tui/) is a view: it reads immutable `View`s and sends commands. It never
touches the controller's objects, the drivers or the simulators. Two sources of views:

- `CellSession`: a live cell. The `CellController` runs on a loop of its own in a background
  thread, because the power source's 10 ms cycle and the interlocks must never wait for the
  screen to redraw. The cell is opened as every cell is (`controller.harness.open_cell`; `--sim`:
  the simulators through `start_simulators`). Snapshots arrive on the bus up to 100 Hz: the
  subscriber only keeps the latest one (and samples the live values into a bounded history at
  10 Hz), so the UI, which reads at its own rate, can never fall behind.
- `ReplaySession`: a fixed, recorded view (snapshot tests, documentation screenshots).

What the controller does, the API does: planning a part (`controller.api.planning.plan_in_child`,
a child process with progress), probing and aligning (`CellController.run_alignment`, or
`align_off_session` on a robot cell), moving a job by an alignment (`aligned_job`), a run's
journal events (`events_after`). The session adds only what a view needs: which thread and loop
each call runs on, the job summary and per-role parameters, the probe plan and alignment as plain
values, the device list with last errors, and a safe stop for quitting mid-build.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import gc
import math
import sys
import threading
import time
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from controller.api import CellJob, Snapshot, aligned_job, events_after, read_job
from controller.tui.trace_ask import TraceAsk
from core.errors import CellError, InputError
from core.realtime import favour, relax_thread

from controller.tui.planning import probe_plan
from controller.tui.replay import ReplaySession  # noqa: F401  (re-exported)
from controller.tui.view import *  # noqa: F401,F403  (the view types, re-exported for the screens)
from controller.tui.view import (DEVICE_WORDS, HISTORY_LEN, PROBE_STATES, SAMPLE_PERIOD_S,
                                 DeviceInfo, JobInfo, LogRow, PlanStatus, Sample, View,
                                 alignment_dict, job_info)
from core.config import load_cell, load_sim
from controller.harness import with_urls


def freeze_heap() -> None:
    """Move every object alive now out of the garbage collector's sight (gc.freeze()).

    A full (generation 2) collection of a process holding Textual's widget tree, the
    simulators and a planned job takes 40-90 ms with the GIL held: long enough to miss the
    power source's watchdog and the cell I/O's 50 ms reply timeout. Frozen objects are never
    scanned, so later collections only walk what is new. Called after start-up, after the
    devices connect and after a job is opened (the big, long-lived allocations).
    """
    gc.freeze()


class CellSession(TraceAsk):
    """A live cell for the TUI: the controller on its own thread and loop, read as `View`s."""

    def __init__(self, cfg: Any = None, *, sim: bool = False, sim_cfg: Any = None, runs_dir: str | Path | None = None,
                 time_scale: float | None = None, faults: str = "", sim_log_dir: str | Path | None = None,
                 sims_beside: bool = False) -> None:
        self.cfg = cfg if cfg is not None else load_cell()
        if time_scale is not None:
            self.cfg = with_urls(self.cfg, {}, time_scale=time_scale)
        self.sim = sim
        # `cell tui --sim`: the simulators run in `cell sim up` beside this process (cfg points at
        # them), so they do not share the interpreter lock with the controller and the screen
        self.sims_beside = sims_beside
        self.sim_cfg = sim_cfg if (sim_cfg is not None or not (sim or sims_beside)) else load_sim()
        self.runs_dir = runs_dir
        self.faults = faults
        self.sim_log_dir = sim_log_dir
        self.harness: Any = None          # the simulators of --sim (tests reach them through it)
        self.ctl: Any = None
        self._cell: contextlib.AsyncExitStack | None = None   # the open cell (controller/harness/cell.py)
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run_loop, name="controller", daemon=True)
        self._lock = threading.Lock()
        self._snap = Snapshot(t=0.0)
        self._seq = 0
        self._hist: deque[Sample] = deque(maxlen=HISTORY_LEN)
        self._last_sample = 0.0
        self._plan = PlanStatus()
        self._job: JobInfo | None = None
        self._cell_job: CellJob | None = None   # the job as the controller opens it (typed)
        self._alignment: dict[str, Any] | None = None
        self._alignment_applied = False  # docs/contract.md §3: one alignment per job, applied once
        self._busy: str | None = None
        self._connect_error: str | None = None
        self._dev_errors: dict[str, str] = {}
        self._ui_log: list[LogRow] = []
        self._build: concurrent.futures.Future[Any] | None = None
        self._unsub: Callable[[], None] | None = None
        self._can_probe = self.cfg.cell.platform == "cnc" or sim or sims_beside
        self._probe_plan = probe_plan(self.cfg, self.sim_cfg) if self._can_probe else ()
        self._probed: list[tuple[str, tuple[float, float, float], float]] = []

    # -- lifecycle ------------------------------------------------------------------------------
    def _run_loop(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()

    def _submit(self, fn: Callable[[], Any]) -> concurrent.futures.Future[Any]:
        """Run `fn()` (a coroutine is awaited) on the controller's loop."""
        async def _do() -> Any:
            res = fn()
            if asyncio.iscoroutine(res):
                res = await res
            return res
        return asyncio.run_coroutine_threadsafe(_do(), self.loop)

    def start(self) -> concurrent.futures.Future[Any]:
        """Start the controller thread (and the simulators with --sim), then connect."""
        # Three busy threads share one GIL here (UI, controller, simulators): hand it over
        # every 2 ms rather than 5 so a device reply waits less behind a screen redraw.
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(0.0005)
        # This (the UI's) thread holds the interpreter lock between the device cycles: at a CPU
        # weight other processes rarely preempt it at while it holds the lock (core/realtime.py
        # favour; docs/controller.md, "Threads that share the interpreter lock")
        self.ui_realtime = favour("terminal UI")
        import planner.job  # noqa: F401  (open_job imports it: not on the controller's loop)

        if not self._thread.is_alive():
            self._thread.start()
        return self.connect()

    def connect(self) -> concurrent.futures.Future[Any]:
        """(Re)connect every device of cell.yaml; a failure is shown, never raised into the UI."""
        if self.build_active():  # never drop the devices under a running build
            fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
            fut.set_exception(CellError(f"'connect' is not allowed in state {self._snap.state}: a build is running"))
            return fut
        self._busy = "connecting"

        async def _do() -> None:
            # lazy: the controller API (drivers, the build runner) loads when the session first needs it,
            # so `cell tui` paints before it; the TUI never imports a driver itself
            from controller.harness import open_cell, start_simulators

            try:
                if self._cell is not None:   # a reconnect: the previous controller closed, the simulators kept
                    cell, self._cell = self._cell, None
                    await cell.aclose()
                    if self._unsub:
                        self._unsub()
                if self.sim and self.harness is None:
                    self.cfg, self.harness = await start_simulators(self.cfg, self.sim_cfg or True,
                                                                    log_dir=self.sim_log_dir, faults=self.faults)
                self._cell = contextlib.AsyncExitStack()
                self.ctl = await self._cell.enter_async_context(
                    open_cell(self.cfg, simulators=self.harness, runs_dir=self.runs_dir, connect=False))
                self._unsub = self.ctl.subscribe(self._on_snapshot)
                await self.ctl.connect()
                self._connect_error = None
                freeze_heap()
                self._note("info", "connected: " + ", ".join(f"{ls.device} {ls.url}" for ls in self.ctl.snapshot().links))
                if self._cell_job is not None:
                    await self._open_job(self._cell_job)
            except Exception as exc:
                msg = str(exc) or exc.__class__.__name__
                self._connect_error = msg
                for dev, words in DEVICE_WORDS.items():
                    if any(w in msg for w in words):
                        self._dev_errors[dev] = msg
                self._note("alarm", f"connect failed: {msg}")
            finally:
                self._busy = None
        return self._submit(_do)

    def close(self, timeout: float = 10.0) -> None:
        """Disconnect (arc off, motion held first when a build runs) and stop the simulators."""
        if not self._thread.is_alive():
            return
        try:
            self.stop_safely().result(timeout)
        except Exception:
            pass
        if self._build is not None:
            # the build's end writes its record (controller/api/): let it finish before the
            # loop stops, so quitting mid-build still leaves report.json, beads.csv and the plots
            try:
                self._build.result(max(timeout, 60.0))
            except Exception:
                pass
        if self._cell is not None:   # the controller closed (controller/harness/cell.py)
            try:
                self._submit(self._cell.aclose).result(timeout)
            except Exception:
                pass
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout)
        if self.harness is not None:
            self.harness.stop()
        # leave the process as it was (tests run many sessions in one process)
        sys.setswitchinterval(getattr(self, "_switch_interval", sys.getswitchinterval()))
        relax_thread()
        gc.unfreeze()

    # -- snapshots ------------------------------------------------------------------------------
    def _on_snapshot(self, s: Snapshot) -> None:
        # Called in the publisher's thread up to 100 Hz: O(1), keeps the latest only.
        self._snap = s
        self._seq += 1
        now = time.monotonic()
        if now - self._last_sample >= SAMPLE_PERIOD_S and (s.current_a is not None or s.temperature_c is not None):
            self._last_sample = now
            self._hist.append(Sample(s.t, s.current_a, s.voltage_v, s.wfs_m_min, s.temperature_c))

    def view(self) -> View:
        s = self._snap
        devices = []
        for ls in s.links:
            devices.append(DeviceInfo(ls.device, ls.url, ls.connected, ls.frames_tx, ls.frames_rx, ls.errors,
                                      ls.queue_free, self._last_error(ls.device, s)))
        if not s.links:
            d = self.cfg.devices
            names = ("robot",) if self.cfg.cell.platform == "robot" else ("cnc",)
            for name in names + ("power_source", "cellio"):
                devices.append(DeviceInfo(name, str(getattr(d, name).url), False,
                                          last_error=self._dev_errors.get(name)))
        return View(snap=s, seq=self._seq, history=tuple(self._hist), plan=self._plan, job=self._job,
                    alignment=self._alignment, alignment_applied=self._alignment_applied, probe_plan=self._probe_plan, probed=tuple(self._probed),
                    can_probe=self._can_probe, platform=self.cfg.cell.platform,
                    devices=tuple(devices), sim=self.sim or self.sims_beside, connect_error=self._connect_error, busy=self._busy)

    def _last_error(self, device: str, s: Snapshot) -> str | None:
        """The device's latest error: kept across reconnects (a new controller starts with no alarms)."""
        for a in s.alarms:
            for dev, words in DEVICE_WORDS.items():
                if any(w in a.message for w in words):
                    self._dev_errors[dev] = a.message
        return self._dev_errors.get(device)

    def _note(self, kind: str, message: str) -> None:
        with self._lock:
            self._ui_log.append(LogRow(-(len(self._ui_log) + 1), time.time(), kind, None, message))

    def log_rows(self, after_id: int = 0, limit: int = 2000) -> list[LogRow]:
        """Journal events with id > after_id (read-only connection; WAL lets it read mid-build)."""
        rd = self._snap.run_dir
        if not rd:
            return []

        rows = events_after(rd, after_id, limit)
        return [LogRow(*r) for r in rows]

    def ui_log(self) -> list[LogRow]:
        """Messages of this session that are not in the journal (connect, plan, refusals)."""
        with self._lock:
            return list(self._ui_log)

    # -- job: open a file, plan an STL ----------------------------------------------------------
    def choose_file(self, path: str | Path, width_mm: float | None = None) -> concurrent.futures.Future[Any]:
        """An STL (to plan) or a job file (opened in the controller at once)."""
        p = Path(path).expanduser()
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        if not p.is_file():
            fut.set_exception(InputError(f"{p}: no such file; give the path of an STL/OBJ/3MF part or a job JSON"))
            return fut
        if p.suffix.lower() in (".stl", ".obj", ".3mf"):
            self._plan = PlanStatus(state="loaded", file=str(p), width_mm=width_mm)
            self._note("info", f"part {p.name} loaded; plan it (width {width_mm} mm)")
            fut.set_result(None)
            return fut
        return self._submit(lambda: self._open_path(p))

    async def _open_path(self, p: Path) -> None:
        # read, checked and hashed off the controller's loop (~0.1 s for the demo part): the power
        # source's 10 ms cycle keeps running meanwhile
        job = await asyncio.get_running_loop().run_in_executor(None, read_job, p)
        self._plan = PlanStatus(state="done", file=str(p))
        self._alignment_applied = False  # a new job: the alignment may be applied to it once
        await self._open_job(job)

    async def _open_job(self, job: CellJob, info: JobInfo | None = None) -> None:
        info = info or job_info(job.job)
        if self.ctl is None or self._snap.state == "disconnected":
            # no cell yet: keep the job, it is opened when the devices connect
            self._cell_job, self._job = job, info
            return
        # open_job checks and journals the whole job: off the controller's loop, so the power
        # source's 10 ms cycle keeps running meanwhile.
        await asyncio.get_running_loop().run_in_executor(None, self.ctl.open_job, job)
        self._cell_job, self._job = job, replace(info, name=self.ctl.snapshot().job_name or info.name)
        freeze_heap()
        self._note("info", f"job {self._job.name} open: {self._job.layers} layers, {self._job.passes} passes")

    def plan(self, width_mm: float | None = None) -> concurrent.futures.Future[Any]:
        """Plan the loaded part (worker thread, progress in the view), then open the job."""
        st = self._plan
        if st.file is None:
            raise InputError("no part loaded: open an STL first")
        width = float(width_mm or st.width_mm or 6.0)
        self._plan = replace(st, state="planning", width_mm=width, done=0, total=0, error=None)
        self._busy = "planning"

        material = self.cfg.cell.material
        part = st.file

        def progress(done: int, total: int) -> None:
            self._plan = replace(self._plan, done=done, total=total)

        def work() -> tuple[CellJob, JobInfo]:
            # the API plans in a child process (controller/api/planning.py): the controller's device
            # cycles keep the interpreter lock; this worker thread only waits for its lines
            from controller.api.planning import plan_in_child

            job = plan_in_child(part, width, material, progress)
            return job, job_info(job.job)

        async def _do() -> None:
            try:
                job, info = await asyncio.get_running_loop().run_in_executor(None, work)
                self._plan = replace(self._plan, state="done")
                self._alignment_applied = False  # a new job: the alignment may be applied to it once
                await self._open_job(job, info)
            except Exception as exc:
                self._plan = replace(self._plan, state="error", error=str(exc))
                self._note("alarm", f"planning failed: {exc}")
                raise
            finally:
                self._busy = None
        return self._submit(_do)

    # -- commands -------------------------------------------------------------------------------
    def command(self, name: str) -> concurrent.futures.Future[Any]:
        """Send a controller command; a refusal comes back as the controller's CellError.

        `start` returns as soon as the build is under way (its end shows in the snapshots).
        """
        # lazy: the controller API (drivers, the build runner) loads when the session first needs it,
        # so `cell tui` paints before it; the TUI never imports a driver itself
        from controller.api import COMMANDS

        if name not in COMMANDS:
            raise InputError(f"unknown command '{name}'")
        if self.ctl is None:
            fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
            fut.set_exception(CellError(f"'{name}' is not allowed: the cell is not connected"))
            return fut
        if name == "start":
            return self._start_build()
        if name == "run_alignment":
            return self._align()
        return self._submit(getattr(self.ctl, name))

    def _start_build(self) -> concurrent.futures.Future[Any]:
        started: concurrent.futures.Future[Any] = concurrent.futures.Future()

        async def _do() -> None:
            task = asyncio.get_running_loop().create_task(self.ctl.start())
            await asyncio.sleep(0)  # let start() check the state: a refusal raises at once
            await asyncio.sleep(0)
            if task.done() and task.exception() is not None:
                started.set_exception(task.exception())
                return
            started.set_result(None)
            try:
                res = await task
                self._note("info", f"build ended: {res.state}, {res.passes_done} passes, {res.layers_done} layers")
            except Exception as exc:
                self._note("alarm", f"build stopped: {exc}")
        self._build = self._submit(_do)
        return started

    def _align(self) -> concurrent.futures.Future[Any]:
        """Probe and align: the facade's `run_alignment` on a CNC cell; on a robot cell with the
        simulators, the routine on the CNC's link as `cell demo` does (the state machine stays put)."""
        self._busy = "aligning"
        self._probed = []

        async def _do() -> Any:
            try:
                if "run_alignment" in self.ctl.allowed_commands():
                    res = await self.ctl.run_alignment()
                else:
                    if self._snap.state not in PROBE_STATES:
                        raise CellError(f"'run_alignment' is not allowed in state {self._snap.state} "
                                        f"(probe with the cell connected and no build running)")
                    # its own loop on a worker thread: the routine's fitting (ICP) must not
                    # hold up the controller's loop and the power source's cycle
                    res = await asyncio.get_running_loop().run_in_executor(None, self._align_on_cnc_link)
                self._alignment = alignment_dict(res)
                if self._alignment is not None:  # when it was probed: the CNC refuses it after a reset/homing
                    self._alignment.setdefault("probed_at", __import__("time").time())
                self._alignment_applied = False
                a = self._alignment or {}
                self._note("info", f"aligned: A {a.get('level_a_deg', math.nan):.4f}°, "
                                   f"B {a.get('level_b_deg', math.nan):.4f}°, face {a.get('face_angle_deg', math.nan):.4f}°")
                return res
            except Exception as exc:
                self._note("alarm", f"alignment failed: {exc}")
                raise
            finally:
                self._busy = None
        return self._submit(_do)

    def _align_on_cnc_link(self) -> Any:
        # lazy: the controller API (drivers, the build runner) loads when the session first needs it,
        # so `cell tui` paints before it; the TUI never imports a driver itself
        from controller.api import align_off_session

        def on_point(pp: Any) -> None:
            pos = tuple(float(c) for c in pp.position)
            self._probed = self._probed + [(str(pp.name), pos, float(pp.spread_mm))]  # type: ignore[list-item]

        return align_off_session(self.cfg, self.sim_cfg, on_point=on_point, timeout_s=120.0)

    def apply_alignment(self) -> concurrent.futures.Future[Any]:
        """Re-open the job moved by the alignment transform (the CAD model moves, not the part)."""
        async def _do() -> None:
            if self._alignment is None or self._cell_job is None:
                raise CellError("nothing to apply: run the alignment and open a job first")
            if self._alignment_applied:
                raise CellError("the alignment is already applied to this job (one alignment per job); "
                                "run the alignment again to re-align")
            tf = self._alignment.get("transform")
            if tf is None:
                raise CellError("the alignment result has no transform")
            a, src = self._alignment, self._cell_job
            record = {"transform": tf, "level_a_deg": a.get("level_a_deg"), "level_b_deg": a.get("level_b_deg"),
                      "probed_at": a.get("probed_at")}
            name = f"{self._job.name if self._job else 'job'}-aligned"
            self._alignment_applied = True  # set before the await: a second key press is refused at once
            try:
                # a new job, read and hashed off the controller's loop; a second alignment is refused
                job = await asyncio.get_running_loop().run_in_executor(
                    None, lambda: aligned_job(src, tf, record, name=name))
                await self._open_job(job)
            except BaseException:
                self._alignment_applied = False
                raise
        return self._submit(_do)

    def stop_safely(self) -> concurrent.futures.Future[Any]:
        """Quitting mid-build: software E-stop (weld start dropped, motion held at once).

        The journal keeps every executed move, so `cell resume` continues where it stopped.
        Nothing happens when no build is running or paused.
        """
        def _do() -> bool:
            s = self.ctl.machine.state if self.ctl is not None else None
            if s is None or not (s.running or s.value == "paused"):
                return False
            self.ctl.estop()
            return True
        return self._submit(_do)

    def build_active(self) -> bool:
        st = self._snap.state
        return st.startswith("running_") or st == "paused"

    def busy_connecting(self) -> bool:
        return self._busy == "connecting"
