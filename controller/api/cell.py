"""The controller's facade for operator views (TUI, CLI): commands, allowed commands, snapshots.

Everything runs on one asyncio loop (the caller's): `await ctl.connect()`, then the command
methods. A view subscribes to immutable `Snapshot`s (controller/runtime/events.py) and asks
`allowed_commands()` to grey out what is not allowed now.

Commands (each refused with a CellError naming the state when not allowed):

- `open_job(job | path)`  a job (read typed once: controller/job/read.py) checked against the
                          cell, its run directory and journal opened → Ready
- `run_alignment()`       probe and align the substrate (CNC, when the routine is installed)
- `start()`               start the build, or continue it from the journal after a reset
                          (awaits the end of the build: Complete, Paused→…, Fault, EStop, Aborted)
- `pause()` / `resume()`  pause at the end of the current bead / go on
- `abort()`               stop at the end of the current bead
- `reset()`               clear a latched Fault / EStop (E-stop input must be released)
- `estop()`               software E-stop: drop start and hold motion at once
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from core.realtime import elevate, is_realtime, lock_sharing_executor, quiet_gc, relax
from controller.report.worker import record_build_end, records_target
from controller.runtime.arc_out import RunOn
from controller.job.check import check_job, job_material
from controller.runtime.build import BuildOptions, BuildResult, BuildRunner
from controller.runtime.layer_control import LayerControl, make_control
from controller.runtime.work import WorkItem
from controller.job.identity import run_dir_for
from controller.runtime.devices import Devices
from controller.runtime.host_witness import HostWitness
from drivers.cyclic import CyclicDevice
from core.config import CellConfig, load_material
from controller.runtime.events import EventBus, LinkStat, Snapshot
from controller.runtime.interlocks import Interlocks
from controller.job.model import CellJob
from controller.job.read import read_job
from controller.journal.reserve import RESERVE_BYTES
from controller.journal.store import Journal
from controller.journal.trace import Trace, require_lot, trace_message
from controller.runtime.machine import CellMachine, State, TransitionRefused
from controller.runtime.resume import remaining_work
from core.errors import CellError
import importlib
from core.config import load_sim
from controller.runtime.arc_handshake import ArcHandshake
from controller.api.offline import align_at
from controller.api.simulated import Simulators

if TYPE_CHECKING:   # the alignment routine loads lazily (ICP, trimesh): its types only
    from controller.align.routine import AlignResult, ProbePlan

COMMANDS = ("open_job", "run_alignment", "start", "pause", "resume", "abort", "reset", "estop")


# The modules a connected cell imports lazily during a build (executors, handshake, readiness,
# 5-axis post): loaded before the device cycles start.
_BUILD_MODULES = ("controller.runtime.arc_handshake", "controller.runtime.readiness", "controller.motion.post5", "core.material")
_PLATFORM_MODULES = {"robot": ("controller.motion.robot",),
                     "cnc": ("controller.motion.cnc", "controller.motion.kinematics")}


def preload_build_modules(platform: str) -> None:
    """Import the modules a build uses before any device cycle runs (no import stalls mid-build)."""

    for name in (*_BUILD_MODULES, *_PLATFORM_MODULES.get(platform, _PLATFORM_MODULES["cnc"])):
        importlib.import_module(name)


class CellController:
    """One cell: devices, state machine, interlocks, journal, build runner, event bus."""

    def __init__(self, cfg: CellConfig, *, runs_dir: str | Path | None = None,
                 options: BuildOptions | None = None, reply_timeout_ms: float | None = None,
                 simulators: Simulators | None = None) -> None:
        self.result_json: dict[str, Any] = {}   # the command line's summary of the last build
        self.cfg = cfg
        self.reply_timeout_ms = reply_timeout_ms   # the bus devices' reply timeout (None: the devices' own)
        self.simulators = simulators    # the simulators it was opened on (controller/harness/cell.py), else None
        self.material = load_material(cfg.cell.material)
        self.runs_dir = Path(runs_dir or cfg.cell.runs_dir)
        mat = self.material
        self.options = options or BuildOptions(
            time_scale=cfg.cell.time_scale, travel_speed_mm_min=cfg.limits.travel_speed_mm_min,
            interpass_limit_c=mat.interpass.max_temperature_c, interpass_dwell_s=mat.interpass.dwell_s,
            arc_efficiency=mat.arc_efficiency,
            run_on=RunOn.from_device(cfg.devices.power_source), tolerance=mat.tolerance,
            progress_timeout_s=cfg.cell.progress_timeout_s)
        self.machine = CellMachine()
        self.bus = EventBus()
        self.devices: Devices | None = None
        self.executor: Any = None
        self.interlocks: Interlocks | None = None
        self.journal: Journal | None = None
        self.job: CellJob | None = None
        self.run_dir: Path | None = None
        self.runner: BuildRunner | None = None
        self.alignment: AlignResult | None = None
        self.arc: Any = None
        self.last_result: BuildResult | None = None
        self.last_report: Path | None = None
        self._stats_task: asyncio.Task[None] | None = None
        self.realtime = ""      # what elevate() obtained for the device cycles (a log line)
        self.witness: HostWitness | None = None   # watches this host's CPUs while connected
        self.opcua: Any = None   # controller.opcua.attach.OpcuaProcess when cell.yaml enables it
        # wire lot, gas, operator (docs/records.md): cell.yaml's; the command or the TUI's dialog replace it
        self.trace = Trace.from_config(cfg)
        self.machine.subscribe(self._on_transition)
        self._publish_state()

    # -- views ------------------------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        return self.bus.latest

    def subscribe(self, fn: Callable[[Snapshot], None]) -> Callable[[], None]:
        return self.bus.subscribe(fn)

    def allowed_commands(self) -> list[str]:
        m, s = self.machine, self.machine.state
        out = []
        if m.can("open_job"):
            out.append("open_job")
        if m.can("probe"):
            out.append("run_alignment")
        if self.job is not None and (m.can("start") or s is State.IDLE):
            out.append("start")
        if s.running and self.runner is not None and not self.runner.pause_requested:
            out.append("pause")
        if s is State.PAUSED:
            out.append("resume")
        if s.running or s is State.PAUSED:
            out.append("abort")
        if m.can("reset"):
            out.append("reset")
        if m.can("estop"):
            out.append("estop")
        return out

    def _on_transition(self, src: State, event: str, dst: State, info: dict[str, Any]) -> None:
        if self.journal is not None:
            cause = f" ({info['cause']})" if "cause" in info else ""
            self.journal.event("transition", f"{src.value} -> {dst.value} on {event}{cause}", state=dst.value)
        self._publish_state()

    def _publish_state(self) -> None:
        self.bus.update(state=self.machine.state.value, allowed_commands=tuple(self.allowed_commands()))

    def _refuse(self, command: str) -> CellError:
        return TransitionRefused(f"'{command}' is not allowed in state {self.machine.state.value} "
                                 f"(allowed now: {', '.join(self.allowed_commands()) or 'none'})")

    # -- connection -------------------------------------------------------------------------------
    async def connect(self, *, resume_ticket: int | None = None, reply_timeout_ms: float | None = None) -> None:
        # Import now what the build needs later: an import while the 10 ms device cycles run
        # holds the loop (and the GIL) for tens of milliseconds, a false "no reply" on the links.
        preload_build_modules(self.cfg.cell.platform)
        # The device cycles run on this thread's loop: real-time priority while connected, so that
        # CPU-bound work beside the controller cannot delay them (docs/false-trips.md).
        self.realtime = elevate("controller device cycles")
        if is_realtime():   # the work it hands off shares the lock: never preempted while holding it
            asyncio.get_running_loop().set_default_executor(lock_sharing_executor())
        slow_ms = os.environ.get("CELL_SLOW_CALLBACK_MS")  # diagnosis: log loop stalls longer than this
        if slow_ms:
            loop = asyncio.get_running_loop()
            loop.set_debug(True)
            loop.slow_callback_duration = float(slow_ms) / 1000.0
        self.bus.update(message=self.realtime)
        if is_realtime() and self.witness is None:
            # a CPU of this host that stops running must not be taken for a silent device
            self.witness = HostWitness()
            self.bus.update(message=self.witness.start())
        self.devices = await Devices.open(self.cfg, self.material, resume_ticket=resume_ticket,
                                          reply_timeout_ms=reply_timeout_ms or self.reply_timeout_ms)
        if self.witness is not None and self.witness.running:
            for dev in (self.devices.power, self.devices.cellio):
                if isinstance(dev, CyclicDevice):
                    dev.host_stalled_s = self.witness.stalled_s
        if self.cfg.cell.platform == "robot":
            # lazy: only the platform's executor is loaded
            from controller.motion.robot import RobotExecutor

            self.executor = RobotExecutor(self.devices.robot_link())
        else:
            # lazy: only the platform's executor is loaded
            from controller.motion.kinematics import Trunnion
            from controller.motion.cnc import CncExecutor

            self.executor = CncExecutor(self.devices.cnc_link(), self.devices.power_source(),
                                        trunnion=Trunnion.from_config(self.cfg.kinematics),
                                        dynamic_power=self.cfg.devices.cnc.process_power == "dynamic")
        self.interlocks = Interlocks(machine=self.machine, journal=self.journal, bus=self.bus,
                                     power=self.devices.power_source(), executor=self.executor,
                                     cellio=self.devices.cellio)
        self.interlocks.arm()

        ilk = self.interlocks
        self.arc = ArcHandshake(self.devices.power_source(), on_fault=lambda exc: ilk.fault(str(exc)))
        self.devices.power_source().set_job(mode=0, job=0)
        self.machine.send("connect")
        self.bus.update(links=self._links())
        self._stats_task = asyncio.get_running_loop().create_task(self._stats_loop())
        if self.cfg.opcua.enabled and self.opcua is None:
            # lazy: OPC UA loads only when cell.yaml enables it
            from controller.opcua.attach import serve

            self.opcua = await serve(self)
        quiet_gc()

    def _links(self) -> tuple[LinkStat, ...]:
        """Link statistics of every connected device, for the views."""
        d = self.devices
        if d is None:
            return ()
        out = []
        if d.robot is not None:
            st = d.robot.stats
            q = d.robot.last_status.queue_free if d.robot.last_status else None
            late, bad = st.timeouts + st.resends, st.naks + st.crc_errors + st.bad_frames
            out.append(LinkStat("robot", d.robot.url, d.robot.connected, st.frames_sent, st.frames_received,
                                late + bad, q, late=late, lost=int(not d.robot.connected), bad=bad))
        if d.cnc is not None:
            out.append(LinkStat("cnc", d.cnc.url, d.cnc.connected))
        if d.power is not None:
            ps = d.power.stats
            out.append(LinkStat("power_source", d.power.url, d.power.error is None, ps.cycles, ps.cycles,
                                ps.late + ps.bad, late=ps.late, lost=ps.lost, bad=ps.bad,
                                max_period_ms=round(ps.max_period_s * 1000, 1),
                                p99_period_ms=ps.period_percentile_ms(99),
                                max_own_period_ms=round(ps.max_own_period_s * 1000, 1),
                                os_delay_ms=round(ps.os_delay_at_max_s * 1000, 1),
                                device_delay_ms=round(ps.device_delay_at_max_s * 1000, 1)))
        if d.cellio is not None:
            cs = d.cellio.stats
            out.append(LinkStat("cellio", d.cellio.url, d.cellio.error is None, cs.cycles, cs.cycles,
                                cs.late + cs.bad, late=cs.late, lost=cs.lost, bad=cs.bad,
                                max_period_ms=round(cs.max_period_s * 1000, 1),
                                p99_period_ms=cs.period_percentile_ms(99),
                                max_own_period_ms=round(cs.max_own_period_s * 1000, 1),
                                os_delay_ms=round(cs.os_delay_at_max_s * 1000, 1),
                                device_delay_ms=round(cs.device_delay_at_max_s * 1000, 1)))
        return tuple(out)

    async def _stats_loop(self) -> None:
        while True:
            await asyncio.sleep(0.5)
            try:
                self.bus.update(links=self._links(), allowed_commands=tuple(self.allowed_commands()))
            except Exception:
                pass

    async def disconnect(self) -> None:
        """Drop every start bit and close the devices (the journal stays open for the report)."""
        if await self._release_devices():
            self.devices = None
        if self.machine.can("disconnect"):
            self.machine.send("disconnect")

    async def close(self) -> None:
        """Drop every start bit, close the devices and the journal."""
        # not disconnect(): its state transition would be journaled (and published) while closing
        await self._release_devices()
        if self.journal is not None:
            self.journal.close()

    async def _release_devices(self) -> bool:
        """Stop the stats loop, disarm the interlocks, drop every start bit and close the devices
        (still referenced); True if there were devices."""
        if self._stats_task is not None:
            self._stats_task.cancel()
            self._stats_task = None
        if self.interlocks is not None:
            self.interlocks.disarm()
        if self.opcua is not None:
            # joining the server's thread takes a while: off the loop, the cycles run meanwhile
            await asyncio.to_thread(self.opcua.stop)
            self.opcua = None
        relax()
        if self.devices is None:
            self._close_witness()
            return False
        try:
            self.devices.power_source().drop_all()
        except Exception:
            pass
        stopping = self.executor.stopping if self.executor is not None else None  # a CNC safe stop ends first
        if stopping is not None and not stopping.done():
            await asyncio.wait([stopping], timeout=30.0)
        await self.devices.close()
        self._close_witness()
        return True

    def _close_witness(self) -> None:
        if self.witness is not None:
            self.witness.close()
            self.witness = None

    # -- commands ---------------------------------------------------------------------------------
    def open_job(self, job: CellJob | str | Path, run_dir: str | Path | None = None) -> Path:
        if not self.machine.can("open_job"):
            raise self._refuse("open_job")
        if not isinstance(job, CellJob):
            job = read_job(job)
        # the whole job against the cell before it can start (once: `cell run` checked it before connecting)
        check_job(job, self.cfg, job_material(job, self.cfg))
        if self.executor is not None:  # the firmware's axes against the job, before any motion (exit 2)
            self.executor.require_job_axes(job)
        self.job = job
        self.run_dir = Path(run_dir) if run_dir else run_dir_for(job, self.runs_dir)
        if self.journal is not None:
            self.journal.close()
        self.journal = Journal(self.run_dir / "journal.sqlite", background=True, reserve_bytes=RESERVE_BYTES)
        self.journal.start_job(job.hash, job.name, self.cfg.cell.platform, job.json)
        if self.interlocks is not None:
            self.interlocks.journal = self.journal
        self.machine.send("open_job")
        done = sum(1 for v in self.journal.pass_progress().values() if v.state == "done")
        self.bus.update(job_name=job.name, job_hash=job.hash, run_dir=str(self.run_dir),
                        layers_total=len(job.layers), passes_total=job.passes_total, passes_done=done)
        return self.run_dir

    async def run_alignment(self, plan: ProbePlan | None = None) -> AlignResult:
        """Probe and align the substrate on the CNC (its touch probe); Probing → Aligned.

        `plan`: the probe plan (default: from the workpiece of config/sim.yaml). On a robot
        cell the CNC link is opened for the routine and closed after it.
        """
        if not self.machine.can("probe"):
            raise self._refuse("run_alignment")
        # lazy: the alignment routine (ICP, trimesh) loads only when a cell is aligned
        from controller.align.routine import align, cad_mesh, plan_for_mesh

        if plan is None:

            plan = plan_for_mesh(cad_mesh(load_sim().cnc.workpiece))
        self.machine.send("probe")
        try:
            cnc = self.devices.cnc if self.devices is not None else None
            if cnc is not None:
                res = await align(cnc, self.cfg, plan)
            else:
                res = await align_at(self.cfg.devices.cnc.url, self.cfg, plan)
            self.alignment = res
        except BaseException as exc:
            if self.machine.can("fault"):
                self.machine.send("fault", cause=f"alignment: {exc}")
            raise
        self.machine.send("aligned")
        if self.journal is not None:
            a = res
            self.journal.event("info", f"aligned: A {a.level_a_deg:.5f}°, B {a.level_b_deg:.5f}°, "
                                       f"face angle {a.face_angle_deg:.5f}°")
        return res

    async def start(self) -> BuildResult:
        """Run (or continue, from the journal) the build until it completes or stops."""
        if self.job is None or self.journal is None:
            raise self._refuse("start")
        if self.machine.state is State.IDLE:
            self.machine.send("open_job")
        if not self.machine.can("start"):
            raise self._refuse("start")
        assert self.devices is not None and self.interlocks is not None
        require_lot(self.cfg, self.trace)   # before any motion (docs/records.md)
        if not self._journal_faults(self.journal, self.interlocks):
            self.last_result = BuildResult(state=self.machine.state.value, layers_done=0, passes_done=0, arc_starts=0)
            return self.last_result
        # the journal's reads below wait for every queued row to be committed (an fsync): wait for
        # that off this loop, which cycles the devices, and read before writing anew (docs/testing.md,
        # "A loop that never blocks")
        await asyncio.to_thread(self.journal.flush)
        for dev in (self.devices.power, self.devices.cellio):
            if isinstance(dev, CyclicDevice):
                dev.restart_periods()   # the record's cycle periods are the build's
        def plan_work(job: CellJob, journal: Journal) -> tuple[LayerControl, list[WorkItem]]:
            # the layers as built (docs/closed-loop.md) and the passes left: off this loop (docs/testing.md)
            control = make_control(self.cfg, job, self.material, journal, self.bus, self.executor)
            return control, control.adjust_work(remaining_work(job, journal), journal.done_passes())

        control, work = await asyncio.to_thread(plan_work, self.job, self.journal)
        self.runner = BuildRunner(job=self.job, journal=self.journal, machine=self.machine, bus=self.bus,
                                  executor=self.executor, power=self.devices.power_source(),
                                  cellio=self.devices.cellio, options=self.options, arc=self.arc,
                                  layers=control, hooks=control)
        quiet_gc()
        self.journal.event("info", f"run {self.journal.run}: {len(work)} passes to deposit")
        trace = self.trace.given(gas=self.material.gas) if self.trace.gas is None else self.trace  # the material's
        self.journal.event("trace", trace_message(trace, self.journal.run))
        self.bus.update(wire_lot=trace.wire_lot, gas=trace.gas, operator=trace.operator)
        self.journal.event("run", json.dumps({"run": self.journal.run, "time_scale": self.options.time_scale,
                                              "passes_left": len(work)}))
        self.interlocks.runner = self.runner
        task = asyncio.get_running_loop().create_task(self.runner.run(work))
        self.interlocks.build_task = task
        try:
            self.last_result = await task
        except CellError as exc:  # a device refused during the build: latch a fault with it
            self.interlocks.trip("fault", str(exc))
            self.last_result = self.runner.result()
        finally:
            self.interlocks.build_task = None
            await self.interlocks.settle()
            if self.runner.closing is not None:  # an interrupted bead's measured length (a CNC: its stop point)
                await asyncio.wait([self.runner.closing], timeout=6.0)
            self._publish_state()
            # the links' health over the run goes into the record (late / lost / bad)
            self.journal.event("links", json.dumps([dataclasses.asdict(x) for x in self._links()]))
        # The build record is written at the end of every build, whoever started it (CLI or TUI),
        # in a worker process (controller/report/worker.py): plotting takes seconds and holds the
        # interpreter lock, and the device cycles (the power source's watchdog counter) run on
        # this loop while the cell stays connected.
        await asyncio.to_thread(self.journal.flush)
        assert self.run_dir is not None
        state = self.last_result.state if self.last_result is not None else None
        self.last_report = await record_build_end(self.journal, self.bus, self.run_dir, self.job, state,
                                                  records_target(self.cfg, self.runs_dir))  # docs/records.md
        return self.last_result

    def write_report(self, plots: bool = True) -> Path:
        """report.json (+ PNGs) in the run directory, from the journal."""
        # lazy: the report modules (matplotlib) load only when a record is written
        from controller.report.summary import write_report

        if self.journal is None or self.run_dir is None:
            raise CellError("no job is open: nothing to report")
        state = self.last_result.state if self.last_result is not None else None
        return write_report(self.journal, self.run_dir, self.job.job if self.job is not None else None, plots=plots,
                            state=state)

    def pause(self) -> None:
        if self.runner is None or not self.machine.state.running:
            raise self._refuse("pause")
        self.runner.request_pause()
        self._publish_state()

    def resume(self) -> None:
        if self.runner is None or self.machine.state is not State.PAUSED:
            raise self._refuse("resume")
        self.runner.resume_from_pause()

    def abort(self) -> None:
        if self.runner is None or not (self.machine.state.running or self.machine.state is State.PAUSED):
            raise self._refuse("abort")
        self.runner.request_abort()

    @property
    def building(self) -> bool:  # a runner exists: a signal stops it on the fault path (runtime/stops.py)
        return self.runner is not None

    def stop_now(self, reason: str) -> bool:
        """A stop from outside (a signal): the fault path, as a lost link takes it: weld start
        dropped, motion held, Fault latched, the cause journaled. False when no device is
        connected (nothing to stop)."""
        if self.interlocks is None:
            return False
        self.interlocks.trip("fault", reason)
        return True

    def _journal_faults(self, journal: Journal, ilk: Interlocks) -> bool:
        """A journal write that fails trips the cell (docs/contract.md §6): the writer thread's error
        goes to this loop. A journal that already failed trips it now: False, no build."""
        loop = asyncio.get_running_loop()

        def on_error(msg: str) -> None:
            loop.call_soon_threadsafe(ilk.fault, msg)

        journal.on_error = on_error
        if journal.failed is not None:
            ilk.fault(journal.failed)
            return False
        return True

    def estop(self) -> None:
        if not self.machine.can("estop") or self.interlocks is None:
            raise self._refuse("estop")
        self.interlocks.trip("estop", "software E-stop")

    async def reset(self) -> None:
        """Clear a latched Fault / EStop: error reset on the power source, flush the motion queue."""
        if not self.machine.can("reset"):
            raise self._refuse("reset")
        released = True
        io = self.devices.cellio if self.devices else None
        if io is not None and not io.inputs.estop_released:
            released = False
        if self.machine.state is State.ESTOP and not released:
            self.machine.send("reset", estop_released=False)  # raises with the reason
        if self.devices is not None:
            await self.arc.reset()
            await self.executor.prepare()
        self.machine.send("reset", estop_released=released)
        if self.journal is not None:
            self.journal.event("info", "reset by the operator", state=self.machine.state.value)

