"""What the operator's terminal UI needs from the controller, and nothing more.

The TUI (controller/tui/) is a view: it reads immutable `View`s and sends commands. It never
touches the controller's objects, the drivers or the simulators. Two sources of views:

- `CellSession`: a live cell. The `CellController` runs on a loop of its own in a background
  thread, because the power source's 10 ms cycle and the interlocks must never wait for the
  screen to redraw. `--sim` starts the in-process simulators through the controller's own
  `SimHarness`. Snapshots arrive on the bus up to 100 Hz: the subscriber only keeps the latest
  one (and samples the live values into a bounded history at 10 Hz), so the UI, which reads at
  its own rate, can never fall behind.
- `ReplaySession`: a fixed, recorded view (snapshot tests, documentation screenshots).

Additions over the facade (controller/api.py): planning an STL with progress, the job summary
and per-role parameters, the probe plan / alignment result as plain values, the device list
with last errors, journal events for the Log screen, and a safe stop for quitting mid-build.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import gc
import math
import sqlite3
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from controller.events import Snapshot
from controller.jobfile import read_job
from planner.errors import CellError, InputError

DEMO_PART = Path(__file__).resolve().parent.parent / "config" / "parts" / "square-hole.stl"
HISTORY_LEN = 300          # samples kept for the live plots (30 s at 10 Hz)
SAMPLE_PERIOD_S = 0.1      # history sampling period (wall seconds)
ROLES = ("perimeter", "infill", "gap")
# Where the substrate may be probed on the CNC's link outside the facade (as `cell demo` does on a
# robot cell): the cell is connected and no build runs.
PROBE_STATES = ("idle", "ready", "aligned", "complete", "aborted")
# How the drivers and the interlocks name each device in their messages.
DEVICE_WORDS = {"robot": ("robot",), "cnc": ("cnc", "CNC"), "power_source": ("power_source", "power source"),
                "cellio": ("cellio", "cell I/O")}


@dataclass(frozen=True)
class Sample:
    """Live process values at one moment (for the Build screen's plots)."""

    t: float
    current_a: float | None
    voltage_v: float | None
    wfs_m_min: float | None
    temperature_c: float | None


@dataclass(frozen=True)
class RoleParams:
    """Process parameters of one bead role in the job (ranges over its passes)."""

    role: str
    passes: int
    width_mm: float
    current_a: tuple[float, float]
    speed_mm_min: tuple[float, float]
    wfs_m_min: tuple[float, float]


@dataclass(frozen=True)
class JobInfo:
    """The open job as the Job screen shows it."""

    name: str
    source: str
    layers: int
    passes: int
    bead: dict
    summary: dict
    roles: tuple[RoleParams, ...]
    # per layer: tuple of (role, ((x, y), ...)) for the terminal preview
    layer_paths: tuple[tuple[tuple[str, tuple[tuple[float, float], ...]], ...], ...] = ()


@dataclass(frozen=True)
class PlanStatus:
    state: str = "none"            # none, loaded (STL chosen, not planned), planning, done, error
    file: str | None = None
    width_mm: float | None = None
    done: int = 0                  # layers sliced so far
    total: int = 0
    error: str | None = None


@dataclass(frozen=True)
class DeviceInfo:
    device: str
    url: str
    connected: bool
    frames_tx: int = 0
    frames_rx: int = 0
    errors: int = 0
    queue_free: int | None = None
    last_error: str | None = None


@dataclass(frozen=True)
class LogRow:
    id: int
    t: float
    kind: str                      # transition, alarm, info, ui
    state: str | None
    message: str
    layer: int | None = None
    pass_: int | None = None


@dataclass(frozen=True)
class View:
    """Everything the TUI draws, at one moment. Plain immutable values."""

    snap: Snapshot
    seq: int = 0                   # snapshots received so far (the UI shows the latest only)
    history: tuple[Sample, ...] = ()
    plan: PlanStatus = PlanStatus()
    job: JobInfo | None = None
    alignment: dict | None = None  # planes, level_a_deg, level_b_deg, face_angle_deg, transform
    probe_plan: tuple[tuple[str, tuple[float, float, float]], ...] = ()
    probed: tuple[tuple[str, tuple[float, float, float], float], ...] = ()  # (name, xyz, spread) as they arrive
    can_probe: bool = False        # a CNC with the touch probe is there (CNC platform, or --sim)
    platform: str = "robot"
    devices: tuple[DeviceInfo, ...] = ()
    sim: bool = False
    connect_error: str | None = None
    busy: str | None = None        # a command in progress (planning, aligning, connecting)

    def allowed(self, command: str) -> bool:
        """Whether a command may be sent now (the controller's allowed_commands, plus UI steps)."""
        if command == "plan":  # planning needs no cell; the job opens when the devices answer
            return self.plan.state in ("loaded", "error", "done") and self.plan.file is not None \
                and self.plan.file.lower().endswith((".stl", ".obj", ".3mf")) and self.busy is None \
                and (self.snap.state == "disconnected" or "open_job" in self.snap.allowed_commands)
        if command == "apply_alignment":
            return self.alignment is not None and self.job is not None and "open_job" in self.snap.allowed_commands
        if command == "connect":  # (re)connect: at start, or after a link loss latched a fault
            return self.snap.state in ("disconnected", "fault") and self.busy is None
        if command == "open":
            return self.busy is None and (self.snap.state == "disconnected" or "open_job" in self.snap.allowed_commands)
        if command == "run_alignment":
            if self.busy is not None or not self.can_probe:
                return False
            return "run_alignment" in self.snap.allowed_commands or self.snap.state in PROBE_STATES
        return command in self.snap.allowed_commands


# -- job helpers (pure) --------------------------------------------------------------------------


def job_info(job: dict, name: str | None = None) -> JobInfo:
    """The summary, per-role parameters and 2-D layer paths of a `cell-job/1` dict."""
    per: dict[str, list[dict]] = {}
    layer_paths = []
    for la in job["layers"]:
        paths = []
        for p in la.get("passes", []):
            per.setdefault(p.get("role", "?"), []).append(p)
            pts = tuple((round(float(q[0]), 3), round(float(q[1]), 3)) for q in p["points"])
            paths.append((p.get("role", "?"), pts))
        layer_paths.append(tuple(paths))

    def rng(ps: list[dict], key: str) -> tuple[float, float]:
        vals = [float(p[key]) for p in ps if key in p]
        return (min(vals), max(vals)) if vals else (math.nan, math.nan)

    roles = tuple(RoleParams(role=r, passes=len(ps), width_mm=rng(ps, "width_mm")[1],
                             current_a=rng(ps, "current_a"), speed_mm_min=rng(ps, "speed_mm_min"),
                             wfs_m_min=rng(ps, "wfs_m_min"))
                  for r, ps in sorted(per.items(), key=lambda kv: (ROLES + (kv[0],)).index(kv[0])))
    src = job.get("source") or {}
    if name is None:
        name = Path(str(src.get("file") or "job")).stem
    return JobInfo(name=name, source=str(src.get("file", "")), layers=len(job["layers"]),
                   passes=sum(len(la.get("passes", [])) for la in job["layers"]), bead=dict(job.get("bead") or {}),
                   summary=dict(job.get("summary") or {}), roles=roles, layer_paths=tuple(layer_paths))


def alignment_dict(result: Any) -> dict | None:
    """An alignment result (AlignResult.to_json(), a dict, a dataclass) as plain values for the view.

    Each plane gets its probed points and their residuals (signed distance along the normal)
    when the result carries them.
    """
    if result is None:
        return None
    if isinstance(result, dict):
        d = dict(result)
    elif hasattr(result, "to_json"):
        d = dict(result.to_json())
    elif hasattr(result, "__dataclass_fields__"):
        d = {k: getattr(result, k) for k in result.__dataclass_fields__}
    else:
        d = {k: v for k, v in vars(result).items() if not k.startswith("_")}
    d = _plain(d)
    pts = d.get("points") if isinstance(d.get("points"), dict) else {}
    planes = d.get("planes") or []
    for pl in planes if isinstance(planes, list) else []:
        if not isinstance(pl, dict):
            continue
        name = pl.get("name")
        if "points" not in pl and name in pts:
            pl["points"] = pts[name]
        n, c = pl.get("normal"), pl.get("point")
        if "residuals" not in pl and pl.get("points") and n and c:
            pl["residuals"] = [sum((p[i] - c[i]) * n[i] for i in range(3)) for p in pl["points"]]
    return d


def _plain(v: Any) -> Any:
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if hasattr(v, "__dataclass_fields__"):
        out = {k: _plain(getattr(v, k)) for k in v.__dataclass_fields__}
        return out
    return v


def probe_plan(cfg: Any, sim_cfg: Any = None) -> tuple[tuple[str, tuple[float, float, float]], ...]:
    """The touches of the alignment routine's plan, as (face, CAD point), for the Align screen.

    The plan is the routine's own (`plan_for_mesh` on the nominal part of the sim config's
    workpiece); nothing on a robot cell, or when the routine is not there.
    """
    try:
        from controller.align.routine import cad_mesh, plan_for_mesh
        from controller.config import load_sim

        wp = (sim_cfg or load_sim()).cnc.workpiece
        plan = plan_for_mesh(cad_mesh(wp))
    except Exception:  # no routine, no workpiece: the screen says the plan is the routine's
        return ()
    out = [("top", (float(x), float(y), plan.top_z)) for x, y in plan.top_xy]
    out += [("side", (plan.side_x, float(y), plan.side_z)) for y in plan.side_y]
    out.append(("tertiary", (plan.tertiary_xy[0], plan.tertiary_xy[1], plan.side_z)))
    return tuple(out)


def _plan_main(argv: list[str]) -> int:
    """Child process of `CellSession.plan`: PATH WIDTH MATERIAL OUT.

    Prints `progress i n` lines, writes the job JSON to OUT, or prints `error <message>`.
    """
    import json
    import sys

    path, width, material, out = argv
    try:
        from controller.config import load_material
        from planner.job import job_to_dict
        from planner.plan import PlanOptions, plan_part

        def progress(i: int, n: int) -> None:
            print(f"progress {i} {n}", flush=True)

        job = plan_part(path, PlanOptions(width_mm=float(width)), load_material(material), progress=progress)
        Path(out).write_text(json.dumps(job_to_dict(job)), encoding="utf-8")
        print("done", flush=True)
        return 0
    except Exception as exc:  # the message goes to the operator
        print("error " + (str(exc) or exc.__class__.__name__).replace("\n", " "), flush=True)
        sys.stdout.flush()
        return 2


def _sim_reply_timeout_ms() -> float:
    """The bus devices' reply timeout with in-process simulators: `cell run --sim`'s own figure."""
    from controller.cli.run import sim_reply_timeout_ms
    return sim_reply_timeout_ms()


def freeze_heap() -> None:
    """Move every object alive now out of the garbage collector's sight (gc.freeze()).

    A full (generation 2) collection of a process holding Textual's widget tree, the
    simulators and a planned job takes 40-90 ms with the GIL held: long enough to miss the
    power source's watchdog and the cell I/O's 50 ms reply timeout. Frozen objects are never
    scanned, so later collections only walk what is new. Called after start-up, after the
    devices connect and after a job is opened (the big, long-lived allocations).
    """
    gc.freeze()


class CellSession:
    """A live cell for the TUI: the controller on its own thread and loop, read as `View`s."""

    def __init__(self, cfg: Any = None, *, sim: bool = False, sim_cfg: Any = None, runs_dir: str | Path | None = None,
                 time_scale: float | None = None, faults: str = "", sim_log_dir: str | Path | None = None) -> None:
        from controller.config import load_cell, load_sim

        self.cfg = cfg if cfg is not None else load_cell()
        if time_scale is not None:
            from controller.cell import with_urls

            self.cfg = with_urls(self.cfg, {}, time_scale=time_scale)
        self.sim = sim
        self.sim_cfg = sim_cfg if (sim_cfg is not None or not sim) else load_sim()
        self.runs_dir = runs_dir
        self.faults = faults
        self.sim_log_dir = sim_log_dir
        self.harness: Any = None          # the SimHarness of --sim (tests reach the simulators through it)
        self.ctl: Any = None
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run_loop, name="controller", daemon=True)
        self._lock = threading.Lock()
        self._snap = Snapshot(t=0.0)
        self._seq = 0
        self._hist: deque[Sample] = deque(maxlen=HISTORY_LEN)
        self._last_sample = 0.0
        self._plan = PlanStatus()
        self._job: JobInfo | None = None
        self._job_dict: dict | None = None
        self._alignment: dict | None = None
        self._busy: str | None = None
        self._connect_error: str | None = None
        self._dev_errors: dict[str, str] = {}
        self._ui_log: list[LogRow] = []
        self._build: concurrent.futures.Future | None = None
        self._unsub: Callable[[], None] | None = None
        self._can_probe = self.cfg.cell.platform == "cnc" or sim
        self._probe_plan = probe_plan(self.cfg, self.sim_cfg) if self._can_probe else ()
        self._probed: list[tuple[str, tuple[float, float, float], float]] = []

    # -- lifecycle ------------------------------------------------------------------------------
    def _run_loop(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()

    def _submit(self, fn: Callable[[], Any]) -> concurrent.futures.Future:
        """Run `fn()` (a coroutine is awaited) on the controller's loop."""
        async def _do() -> Any:
            res = fn()
            if asyncio.iscoroutine(res):
                res = await res
            return res
        return asyncio.run_coroutine_threadsafe(_do(), self.loop)

    def start(self) -> concurrent.futures.Future:
        """Start the controller thread (and the simulators with --sim), then connect."""
        # Three busy threads share one GIL here (UI, controller, simulators): hand it over
        # every 2 ms rather than 5 so a device reply waits less behind a screen redraw.
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(0.002)
        import planner.job  # noqa: F401  (open_job imports it: not on the controller's loop)

        if not self._thread.is_alive():
            self._thread.start()
        return self.connect()

    def connect(self) -> concurrent.futures.Future:
        """(Re)connect every device of cell.yaml; a failure is shown, never raised into the UI."""
        if self.build_active():  # never drop the devices under a running build
            fut: concurrent.futures.Future = concurrent.futures.Future()
            fut.set_exception(CellError(f"'connect' is not allowed in state {self._snap.state}: a build is running"))
            return fut
        self._busy = "connecting"

        async def _do() -> None:
            from controller.api import CellController

            try:
                if self.ctl is not None:
                    await self.ctl.close()
                    if self._unsub:
                        self._unsub()
                if self.sim and self.harness is None:
                    from controller.cell import SimHarness, with_urls

                    self.harness = SimHarness(self.cfg, self.sim_cfg, log_dir=self.sim_log_dir, faults=self.faults)
                    urls = await asyncio.get_running_loop().run_in_executor(None, self.harness.start)
                    self.cfg = with_urls(self.cfg, urls)
                self.ctl = CellController(self.cfg, runs_dir=self.runs_dir)
                self._unsub = self.ctl.subscribe(self._on_snapshot)
                await self.ctl.connect(reply_timeout_ms=_sim_reply_timeout_ms() if self.sim else None)
                self._connect_error = None
                freeze_heap()
                self._note("info", "connected: " + ", ".join(f"{ls.device} {ls.url}" for ls in self.ctl.snapshot().links))
                if self._job_dict is not None:
                    await self._open_dict(self._job_dict)
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
        if self.ctl is not None:
            try:
                self._submit(self.ctl.close).result(timeout)
            except Exception:
                pass
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout)
        if self.harness is not None:
            self.harness.stop()
        # leave the process as it was (tests run many sessions in one process)
        sys.setswitchinterval(getattr(self, "_switch_interval", sys.getswitchinterval()))
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
                    alignment=self._alignment, probe_plan=self._probe_plan, probed=tuple(self._probed),
                    can_probe=self._can_probe, platform=self.cfg.cell.platform,
                    devices=tuple(devices), sim=self.sim, connect_error=self._connect_error, busy=self._busy)

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
        path = Path(rd) / "journal.sqlite"
        if not path.exists():
            return []
        try:
            db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=0.2)
            try:
                rows = db.execute("SELECT id, t, kind, state, message, layer, pass FROM events WHERE id > ? "
                                  "ORDER BY id LIMIT ?", (after_id, limit)).fetchall()
            finally:
                db.close()
        except sqlite3.Error:
            return []
        return [LogRow(*r) for r in rows]

    def ui_log(self) -> list[LogRow]:
        """Messages of this session that are not in the journal (connect, plan, refusals)."""
        with self._lock:
            return list(self._ui_log)

    # -- job: open a file, plan an STL ----------------------------------------------------------
    def choose_file(self, path: str | Path, width_mm: float | None = None) -> concurrent.futures.Future:
        """An STL (to plan) or a job file (opened in the controller at once)."""
        p = Path(path).expanduser()
        fut: concurrent.futures.Future = concurrent.futures.Future()
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
        job = read_job(p)
        self._plan = PlanStatus(state="done", file=str(p))
        await self._open_dict(job)

    async def _open_dict(self, job: dict, info: JobInfo | None = None) -> None:
        info = info or job_info(job)
        if self.ctl is None or self._snap.state == "disconnected":
            # no cell yet: keep the job, it is opened when the devices connect
            self._job_dict, self._job = job, info
            return
        # open_job hashes and journals the whole job (~0.1 s for the demo part): off the
        # controller's loop, so the power source's 10 ms cycle keeps running meanwhile.
        await asyncio.get_running_loop().run_in_executor(None, self.ctl.open_job, job)
        self._job_dict, self._job = job, replace(info, name=self.ctl.snapshot().job_name or info.name)
        freeze_heap()
        self._note("info", f"job {self._job.name} open: {self._job.layers} layers, {self._job.passes} passes")

    def plan(self, width_mm: float | None = None) -> concurrent.futures.Future:
        """Plan the loaded part (worker thread, progress in the view), then open the job."""
        st = self._plan
        if st.file is None:
            raise InputError("no part loaded: open an STL first")
        width = float(width_mm or st.width_mm or 6.0)
        self._plan = replace(st, state="planning", width_mm=width, done=0, total=0, error=None)
        self._busy = "planning"

        material = self.cfg.cell.material

        def work() -> tuple[dict, JobInfo]:
            # Planning is CPU-bound: in a thread it would hold the GIL long enough to starve
            # the power source's 10 ms cycle and the cell I/O poll (a link timeout, a fault).
            # It runs in a child process; progress comes back line by line on its stdout.
            import json
            import subprocess
            import sys
            import tempfile

            with tempfile.TemporaryDirectory(prefix="cell-plan-") as tmp:
                out = Path(tmp) / "job.json"
                proc = subprocess.Popen([sys.executable, "-m", "controller.tui_adapter", "plan", str(st.file),
                                         str(width), material, str(out)],
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                error = None
                assert proc.stdout is not None
                for line in proc.stdout:
                    word, _, rest = line.strip().partition(" ")
                    if word == "progress":
                        i, n = rest.split()
                        self._plan = replace(self._plan, done=int(i), total=int(n))
                    elif word == "error":
                        error = rest
                err_text = proc.stderr.read() if proc.stderr else ""
                proc.wait()
                if error is not None:
                    raise CellError(error)
                if proc.returncode != 0 or not out.exists():
                    last = err_text.strip().splitlines()[-1:] or ["no output"]
                    raise CellError(f"planning {st.file}: the planner stopped ({last[0]})")
                job = json.loads(out.read_text(encoding="utf-8"))
            return job, job_info(job)

        async def _do() -> None:
            try:
                job, info = await asyncio.get_running_loop().run_in_executor(None, work)
                self._plan = replace(self._plan, state="done")
                await self._open_dict(job, info)
            except Exception as exc:
                self._plan = replace(self._plan, state="error", error=str(exc))
                self._note("alarm", f"planning failed: {exc}")
                raise
            finally:
                self._busy = None
        return self._submit(_do)

    # -- commands -------------------------------------------------------------------------------
    def command(self, name: str) -> concurrent.futures.Future:
        """Send a controller command; a refusal comes back as the controller's CellError.

        `start` returns as soon as the build is under way (its end shows in the snapshots).
        """
        from controller.api import COMMANDS

        if name not in COMMANDS:
            raise InputError(f"unknown command '{name}'")
        if self.ctl is None:
            fut: concurrent.futures.Future = concurrent.futures.Future()
            fut.set_exception(CellError(f"'{name}' is not allowed: the cell is not connected"))
            return fut
        if name == "start":
            return self._start_build()
        if name == "run_alignment":
            return self._align()
        return self._submit(getattr(self.ctl, name))

    def _start_build(self) -> concurrent.futures.Future:
        started: concurrent.futures.Future = concurrent.futures.Future()

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

    def _align(self) -> concurrent.futures.Future:
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
        from controller.align.routine import align, cad_mesh, plan_for_mesh
        from controller.config import load_sim
        from drivers.grbl import CncLink

        plan = plan_for_mesh(cad_mesh((self.sim_cfg or load_sim()).cnc.workpiece))
        dev = self.cfg.devices.cnc

        def on_point(pp: Any) -> None:
            pos = tuple(float(c) for c in pp.position)
            self._probed = self._probed + [(str(pp.name), pos, float(pp.spread_mm))]  # type: ignore[list-item]

        async def run() -> Any:
            link = CncLink(dev.url, baud=dev.baud, rx_buffer_bytes=dev.rx_buffer_bytes, status_hz=dev.status_hz)
            await link.connect()
            try:
                return await asyncio.wait_for(align(link, self.cfg, plan, on_point=on_point), 120.0)
            finally:
                await link.close()
        try:
            return asyncio.run(run())
        except asyncio.TimeoutError:
            raise CellError("alignment: the probe cycle did not finish within 120 s; check the CNC link") from None

    def apply_alignment(self) -> concurrent.futures.Future:
        """Re-open the job moved by the alignment transform (the CAD model moves, not the part)."""
        async def _do() -> None:
            from controller.align.kinematics import apply_to_job

            if self._alignment is None or self._job_dict is None:
                raise CellError("nothing to apply: run the alignment and open a job first")
            tf = self._alignment.get("transform")
            if tf is None:
                raise CellError("the alignment result has no transform")
            job = apply_to_job(self._job_dict, tf)
            job["name"] = f"{self._job.name if self._job else 'job'}-aligned"
            await self._open_dict(job)
        return self._submit(_do)

    def stop_safely(self) -> concurrent.futures.Future:
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


class ReplaySession:
    """A recorded, fixed view: for snapshot tests and screenshots (no clock, no devices)."""

    def __init__(self, view: View, log: list[LogRow] | None = None) -> None:
        self._view = view
        self._log = list(log or [])
        self.refused: list[str] = []

    def start(self) -> concurrent.futures.Future:
        f: concurrent.futures.Future = concurrent.futures.Future()
        f.set_result(None)
        return f

    def view(self) -> View:
        return self._view

    def log_rows(self, after_id: int = 0, limit: int = 2000) -> list[LogRow]:
        return [r for r in self._log if r.id > after_id][:limit]

    def ui_log(self) -> list[LogRow]:
        return []

    def _refuse(self, what: str) -> concurrent.futures.Future:
        self.refused.append(what)
        f: concurrent.futures.Future = concurrent.futures.Future()
        f.set_exception(CellError(f"'{what}' is not available in a recorded view"))
        return f

    def command(self, name: str) -> concurrent.futures.Future:
        return self._refuse(name)

    def choose_file(self, path: str | Path, width_mm: float | None = None) -> concurrent.futures.Future:
        return self._refuse("open")

    def plan(self, width_mm: float | None = None) -> concurrent.futures.Future:
        return self._refuse("plan")

    def connect(self) -> concurrent.futures.Future:
        return self._refuse("connect")

    def apply_alignment(self) -> concurrent.futures.Future:
        return self._refuse("apply_alignment")

    def stop_safely(self) -> concurrent.futures.Future:
        f: concurrent.futures.Future = concurrent.futures.Future()
        f.set_result(False)
        return f

    def build_active(self) -> bool:
        st = self._view.snap.state
        return st.startswith("running_") or st == "paused"

    def close(self, timeout: float = 10.0) -> None:
        pass


if __name__ == "__main__":
    if len(sys.argv) == 6 and sys.argv[1] == "plan":
        raise SystemExit(_plan_main(sys.argv[2:]))
    sys.stderr.write("usage: python -m controller.tui_adapter plan PATH WIDTH MATERIAL OUT\n")
    raise SystemExit(2)
