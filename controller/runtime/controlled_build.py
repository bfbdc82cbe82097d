"""The build runner with the layer-height control (docs/closed-loop.md) hooked in.

`ControlledRunner` is the `BuildRunner` (controller/runtime/build.py) with four hooks, so the
runner itself stays as it is: its `layers` are the control's (layer i as built: z offset and
travel-speed trim applied, top layers added or dropped), each bead's arc-stable current samples
go to the stick-out estimate, and after each pass the control may close a layer (measure, decide
the next layer, edit the remaining work in place) and ask for a pause with its message, honoured
at the end of the bead like an operator's pause (before the next layer).
"""
from __future__ import annotations

from typing import Any, Sequence

from controller.align.layer_probe import probe_layer_top
from controller.job.model import CellJob
from controller.ports import MotionExecutor
from drivers.power import PowerStatus
from controller.journal.store import Journal
from controller.runtime.build import BuildResult, BuildRunner, WorkItem
from controller.runtime.events import EventBus
from controller.runtime.layer_control import LayerControl, ProbeFn, Spot
from core.config import CellConfig
from core.material import Material

__all__ = ["ControlledRunner", "make_control"]


class ControlledRunner(BuildRunner):
    def __init__(self, *, control: LayerControl, **kw: Any) -> None:
        super().__init__(hooks=control, **kw)
        self.lc = control
        self.layers = control.layers
        self.totals = (len(self.layers), sum(len(la.passes) for la in list.__iter__(self.layers)))
        self._work: list[WorkItem] = []
        self._k = -1
        self._currents: list[float] = []

    async def run(self, work: list[WorkItem]) -> BuildResult:
        self._work, self._k = work, -1   # the list the runner walks: the control edits its tail
        return await super().run(work)

    async def _one_pass(self, item: WorkItem) -> None:
        self._k += 1
        self._currents = []
        await super()._one_pass(item)
        why = await self.lc.after_pass(item, self._work, self._k)
        if why is not None:
            self.journal.event("alarm", why, layer=item.layer)
            self.bus.alarm("warning", why, layer=item.layer)
            self.pause_cause, self.pause_requested = why, True

    def resume_from_pause(self) -> None:
        self.pause_cause = None
        super().resume_from_pause()

    def _on_power(self, st: PowerStatus) -> None:
        if self._bead is not None and st.arc_stable and self._arc_lit:
            self._currents.append(float(st.current_a))
        super()._on_power(st)

    def _close_bead(self, la: int, pa: int, pts: Any, i0: int, i1: int, speed: float,
                    interrupted: bool) -> dict[str, Any] | None:
        had = self._bead is not None
        stats = super()._close_bead(la, pa, pts, i0, i1, speed, interrupted)
        if had and not interrupted:
            self.lc.bead_closed(la, pa, self._currents, self.layers[la].passes[pa].wfs_m_min)
        return stats


def make_control(cfg: CellConfig, job: CellJob, material: Material, journal: Journal, bus: EventBus | None,
                 executor: MotionExecutor) -> LayerControl:
    """The build's layer control (restored from the journal on a resume); the CNC's probe when it has one."""
    pc = cfg.process_control
    probe: ProbeFn | None = None
    link = executor.cnc_link
    if link is not None:
        async def probe(la: int, spots: Sequence[Spot]) -> list[float]:
            return await probe_layer_top(link, cfg.probe, list(spots), cfg.probe.clearance_mm, name=f"layer {la} top")
    lc = LayerControl(job=job, cfg=pc, material=material, platform=cfg.cell.platform, journal=journal, bus=bus,
                      max_speed_mm_min=cfg.limits.max_speed_mm_min, probe=probe)
    lc.restore()
    return lc
