"""Build execution: layer by layer, pass by pass, under the state machine and the journal.

The runner is platform-neutral; an executor (controller/motion/robot.py, cnc.py) drives the motion
through the `MotionExecutor` port (controller/ports.py). This module sequences the work: before a
layer's first arc the interpass rule, each pass deposited by the pass execution
(controller/runtime/pass_run.py), after each pass the process control's verdict (go on, pause,
other passes next) and the operator's pause and abort, honoured at the end of a bead.

The layers come from a `LayerSource` and a process control attaches through `BuildHooks`
(controller/runtime/hooks.py); without them the job's layers are laid as planned.
"""
from __future__ import annotations

import asyncio
import time
from typing import Callable

from controller.job.model import CellJob
from controller.journal.store import Journal
from controller.ports import ArcControl, CellIOPort, MotionExecutor, PowerSourcePort
from controller.runtime.arc_handshake import ArcHandshake
from controller.runtime.events import EventBus
from controller.runtime.hooks import BuildHooks, LayerSource, NoHooks, PlannedLayers
from controller.runtime.interpass import interpass_wait
from controller.runtime.machine import CellMachine, State
from controller.runtime.pass_run import PassRunner
from controller.runtime.progress import progress_timeout_s
from controller.runtime.readiness import ensure_ready
from controller.runtime.work import BuildError, BuildOptions, BuildResult, Interrupted, WorkItem

__all__ = ["BuildError", "BuildOptions", "BuildResult", "BuildRunner", "Interrupted", "WorkItem"]


class BuildRunner:
    """Runs a list of work items; one instance per run (first run or resume)."""

    def __init__(self, *, job: CellJob, journal: Journal, machine: CellMachine, bus: EventBus,
                 executor: MotionExecutor, power: PowerSourcePort, cellio: CellIOPort | None = None,
                 options: BuildOptions | None = None, arc: ArcControl | None = None,
                 log: Callable[[str], None] | None = None, layers: LayerSource | None = None,
                 hooks: BuildHooks | None = None) -> None:
        self.job, self.journal, self.m, self.bus = job, journal, machine, bus
        self.ex, self.power = executor, power
        self.o = options or BuildOptions()
        self.arc: ArcControl = arc or ArcHandshake(power)
        self.log = log or (lambda _s: None)
        self.layers: LayerSource = layers or PlannedLayers(job.layers)
        self.hooks: BuildHooks = hooks or NoHooks()
        self.pause_requested = self.abort_requested = False
        self.pause_cause: str | None = None   # a control's pause (None: the operator's)
        self._resume_evt = asyncio.Event()
        self.tripped: str | None = None      # the interlock's message once tripped
        n = self.layers.layer_count()
        self.totals = (n, sum(self.layers.passes_in(i) for i in range(n)))
        progress = journal.pass_progress()
        self.done = {k for k, v in progress.items() if v.state == "done"}
        # counted here, not read back: a journal read on this loop waits for every queued write
        # to be committed (fsync), which would stall the device cycles at the end of the build
        self._defects_before = journal.defect_count()
        self.passes = PassRunner(journal=journal, machine=machine, bus=bus, executor=executor, power=power,
                                 cellio=cellio, options=self.o, arc=self.arc, hooks=self.hooks,
                                 progress_s=progress_timeout_s(job, self.o.max_step_mm, self.o.progress_timeout_s),
                                 journaled=set(progress))

    # -- what the interlocks and the views read --------------------------------------------------
    @property
    def current(self) -> WorkItem | None:
        """The pass under way (or the last one)."""
        return self.passes.current

    @property
    def closing(self) -> asyncio.Task[None] | None:
        """An interrupted bead's close (it awaits the held position)."""
        return self.passes.closing

    # -- operator requests (honoured at the end of the current bead) -------------------------
    def request_pause(self) -> None:
        self.pause_requested = True

    def request_abort(self) -> None:
        self.abort_requested = True
        self._resume_evt.set()

    def resume_from_pause(self) -> None:
        self.pause_requested = False
        self.pause_cause = None
        self._resume_evt.set()

    # -- the run --------------------------------------------------------------------------------
    async def _before_motion(self) -> None:
        """Everything checked and prepared before the first move (5-axis post, devices ready)."""
        await self.ex.post_job(self.job, self.o.max_step_mm)  # 5-axis: machine axes, refused before any motion
        await self._arc_out()
        await self.ex.prepare()
        await ensure_ready(self.ex, self.power, self.journal, reset_errors=self.o.reset_errors, arc=self.arc)
        await self.hooks.before_motion()   # e.g. the path loop's CNC homed before its first touch

    async def run(self, work: list[WorkItem]) -> BuildResult:
        self.passes.attach()
        self.bus.update(layers_total=self.totals[0], passes_total=self.totals[1],
                        passes_done=len(self.done), layers_done=self._layers_done())
        try:
            await self._before_motion()
            if self.m.state is not State.RUNNING_WAIT:
                self.m.send("start")
            return await self._sequence(list(work))
        except (Interrupted, asyncio.CancelledError):
            if self.tripped is None:
                raise
            return self.result()
        finally:
            self.passes.detach()

    async def _sequence(self, work: list[WorkItem]) -> BuildResult:
        """The work in order: a layer's interpass before its first pass, the control's verdict
        and the operator's requests after each pass."""
        prev_layer: int | None = None
        k = 0
        while k < len(work):
            item = work[k]
            if item.layer != prev_layer:
                if prev_layer is not None and self.m.can("next_layer"):
                    self.m.send("next_layer")
                self.bus.update(layer=item.layer, pass_=item.pass_,
                                passes_in_layer=len(self.layers.layer(item.layer).passes))
                await self._interpass(item.layer)
                prev_layer = item.layer
            await self.passes.run(item, self.layers.layer(item.layer))
            self._pass_done(item.layer, item.pass_)
            await self._after_pass(item, work, k)
            if k == len(work) - 1:
                break
            if self.abort_requested:
                # journaled once, by the controller's transition listener, with its cause
                self.m.send("abort", cause="by the operator")
                return self.result()
            if self.pause_requested:
                self.m.send("pause", cause=self.pause_cause or "at the end of a bead")
                self._resume_evt.clear()
                await self._resume_evt.wait()
                if self.abort_requested:
                    self.m.send("abort", cause="by the operator")
                    return self.result()
                self.m.send("resume")
                prev_layer = None if work[k + 1].layer != item.layer else prev_layer
            k += 1
        await self.journal.committed()  # never `complete` with the journal incomplete
        if self.m.can("complete"):
            self.m.send("complete", cause="every pass done")
        return self.result()

    async def _after_pass(self, item: WorkItem, work: list[WorkItem], k: int) -> None:
        """The process control's verdict on pass `item` (work[k]): other work next, a pause."""
        verdict = await self.hooks.after_pass(item, work[k + 1:])
        if verdict.rest is not None:
            work[k + 1:] = verdict.rest
        if verdict.pause is not None:
            self.journal.event("alarm", verdict.pause, layer=item.layer)
            self.bus.alarm("warning", verdict.pause, layer=item.layer)
            self.pause_cause, self.pause_requested = verdict.pause, True

    def result(self) -> BuildResult:
        """Where the build stands: its state, the layers and passes done, arcs struck, defects."""
        return BuildResult(state=self.m.state.value, layers_done=self._layers_done(),
                           passes_done=len(self.done), arc_starts=self.passes.arc_starts,
                           defects=self._defects_before + self.passes.defects_new)

    def _layers_done(self) -> int:
        n = 0
        for li in range(self.layers.layer_count()):
            if all((li, pi) in self.done for pi in range(self.layers.passes_in(li))):
                n += 1
            else:
                break
        return n

    async def _interpass(self, layer: int) -> None:
        """Before a layer's first arc: pyrometer below the limit, or the dwell without a reading."""
        rule = self.layers.layer(layer).interpass
        await interpass_wait(layer, rule.max_temperature_c if rule is not None else self.o.interpass_limit_c,
                             rule.dwell_s if rule is not None else self.o.interpass_dwell_s, self.o.interpass_timeout_s,
                             self.o.time_scale, self.passes.temperature, self.journal, self.bus)

    async def _arc_out(self) -> None:
        """Before a run: let an arc a crash left burning go out, so the robot's position read
        next bounds the deposit (the new power cycle carries weld start 0)."""
        st = self.power.status
        t0 = time.monotonic()
        while st is not None and st.arc_stable and time.monotonic() - t0 < 2.0:
            st = await self.power.next_status()

    def _pass_done(self, la: int, pa: int) -> None:
        self.journal.pass_state(la, pa, "done")
        self.done.add((la, pa))
        self.bus.update(passes_done=len(self.done), layers_done=self._layers_done())

    # -- interlock side -------------------------------------------------------------------------
    def interrupted(self, message: str) -> None:
        """Called by the interlocks after they held motion and dropped the start."""
        self.tripped = message
        self.passes.interrupted(message)
