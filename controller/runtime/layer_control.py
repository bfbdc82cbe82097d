"""Closed-loop layer height (docs/contract.md §6b, docs/closed-loop.md): the build runner's process control.

It is the build runner's layer source and hooks (controller/runtime/hooks.py), for the `open`,
`layer` and `path` modes alike: the runner asks it for each layer as built (`layer(i)`: the
layer's z offset and travel-speed trim applied, journaled before its first bead), tells it every
arc-stable sample (`arc_sample`, forwarded to the path loop) and each bead's current samples
(`bead_closed`: the robot's stick-out through the arc) and, after each pass, lets it close a
layer (`after_pass`): measure the layer's top (robot: from the beads' stick-out; CNC: probed every
`probe_every_layers`), update the gain, choose the next layer's z and the remaining layers' trim /
count (controller/runtime/layer_plan.py), record it, and answer a pause message when the stick-out
left `ctwd_window_mm` or the correction needed exceeds `max_z_correction_mm`, and the work to lay
next when top layers were added or dropped. `make_control` builds it for a cell.

Journal (events, one JSON object per message; nothing of the schema changes):
- `layer_plan` {layer, z_offset_mm, speed_factor}: written before the layer's first bead; a
  resumed build reads it back, so a layer is never laid at another height after a restart;
- `stick_out` {layer, pass, stick_out_mm, current_a, n, sigma_mm}: per bead (through the arc);
- `layer` {layer, planned_top_mm, z_mm, measured_top_mm, source, stick_out_mm, ...}: per layer;
- `layer_count` {after_layer, layers}: top layers added or dropped.
`open` mode keeps the plan (no copy of a pass, no pause): it only records the estimates.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import replace
from typing import Any, Awaitable, Callable, Sequence

import numpy as np

from controller.align.layer_probe import probe_layer_top, probe_spots
from controller.align.watched import home
from controller.job.model import CellJob
from controller.journal.store import Journal
from controller.ports import MotionExecutor
from controller.runtime.hooks import GO_ON, AfterPass
from controller.runtime.work import WorkItem
from controller.runtime.events import EventBus
from controller.runtime.layer_plan import (
    adjusted_layer, build_layers, decide, layer_height, layer_z, rise_factor, fit_gain, speed_for,
)
from controller.runtime.path_control import PathControl
from controller.runtime.path_probe import TouchPlan, expected_tops, touch_tops
from controller.runtime.stickout import StickOut, StickOutEstimator
from core.config import CellConfig, ProcessControl
from core.material import Material
from planner.job import Layer, Pass

Spot = tuple[float, float, float]
PATH_PROBE_CLEARANCE_MM = 1.5   # path mode: the head travels this far above the planned top (or the neighbour just touched)
PATH_PROBE_MAX_EXTRA_HOP_MM = 5.0   # ... plus the most a top stood above plan and expectation on the layer before, up to this
PATH_PROBE_FEED_MM_MIN = 1800.0   # its touch's feed (the probe latches the trip; grbl's report is the latched position)
ProbeFn = Callable[[int, Sequence[Spot]], Awaitable[list[float]]]   # (layer, spots on it) -> probed tops


def layers_as_commanded(job: CellJob) -> list[Layer]:
    """The job's layers with each `z_mm` in the frame of its points, the frame the machine is
    commanded in and the probe reads: an aligned job's points are machine positions
    (`apply_to_job`) while its layers' z_mm stay in the CAD frame (a repair job's pocket floor at
    z = -4 mm in the CAD frame was z = -2 mm on the machine). Unaligned jobs: the same list."""
    al = job.alignment
    if al is None or al.transform is None:
        return list(job.layers)
    m = np.asarray(al.transform, dtype=float)
    pts = [p.points[:, :3] for la in job.layers for p in la.passes]
    allp = np.concatenate(pts) if pts else np.zeros((0, 3))
    # the CAD xy under the deposit's middle: a leveled table maps CAD z to machine z whatever the
    # xy, up to the leveling's residual
    mid = np.linalg.inv(m) @ np.r_[allp.mean(axis=0), 1.0] if len(allp) else np.zeros(4)
    return [replace(la, z_mm=float(m[2] @ np.array([mid[0], mid[1], la.z_mm, 1.0]))) for la in job.layers]


def _r(x: float | None, nd: int = 4) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


class LayerControl:
    """One build's layer-height control; `open` records only."""

    def __init__(self, *, job: CellJob, cfg: ProcessControl, material: Material, platform: str, journal: Journal,
                 bus: EventBus | None = None, max_speed_mm_min: float = 1e9, probe: ProbeFn | None = None,
                 prepare: Callable[[], Awaitable[None]] | None = None) -> None:
        self.cfg, self.platform, self.journal, self.bus, self.probe = cfg, platform, journal, bus, probe
        self.prepare = prepare     # the probe's device readied before the first move (the CNC homed)
        self.closed = cfg.mode in ("layer", "path")
        self.job_layers: list[Layer] = layers_as_commanded(job)
        self.n_planned = len(self.job_layers)
        self.n_total = self.n_planned
        self.layers: list[Layer] = list(self.job_layers)   # the plan: planned layers, then added ones
        self.est = StickOutEstimator(material, cfg.steady_share)
        self.l0 = self.est.nominal_mm
        self.p = 1.0   # the rise follows the metal (controller/runtime/layer_plan.py)
        top_speed = max(float(p.speeds().max()) for la in self.job_layers for p in la.passes)
        trim = cfg.speed_trim_pct / 100.0
        self.k_range = (max(1.0 - trim, 0.05), max(min(1.0 + trim, max_speed_mm_min / top_speed), 1e-3))
        self.final_mm = layer_z(self.job_layers[-1])
        self.applied: dict[int, tuple[float, float]] = {}
        self._built: dict[int, Layer] = {}
        self.next_dz, self.next_k = 0.0, 1.0
        self.gain = 1.0
        first = self.job_layers[0]
        self.top = layer_z(first) - layer_height(first)        # the substrate under the plan
        self.expected_cum = 0.0                                 # the model's rise so far (Σ h·f(k))
        self.hist: list[tuple[float, float]] = [(0.0, self.top)]  # (model rise, measured top)
        self.beads: dict[int, list[StickOut]] = {}
        self.records: list[dict[str, Any]] = []
        width = min((p.width_mm for la in self.job_layers for p in la.passes), default=7.0)
        self._probed: dict[int, tuple[list[Spot], list[float]]] = {}
        self.probe_s: dict[int, float] = {}     # CNC: wall seconds each layer's probing took
        self._rows: dict[int, list[tuple[float, float, float, float]]] = {}   # path mode: a layer's bins, read once
        self.path = PathControl(cfg=cfg, journal=journal, bus=bus, platform=platform, est=self.est, width_mm=width,
                                max_speed_mm_min=max_speed_mm_min) if cfg.mode == "path" else None

    # -- journal --------------------------------------------------------------------------------
    def _event(self, kind: str, data: dict[str, Any], layer: int | None = None) -> None:
        self.journal.event(kind, json.dumps(data, sort_keys=True), layer=layer)

    def restore(self) -> None:
        """A resumed build: the corrections already applied and the latest state, from the journal."""
        rows = self.journal.query("SELECT kind, message FROM events WHERE kind IN "
                                  "('layer_plan', 'layer', 'layer_count') ORDER BY id")
        for kind, msg in rows:
            d = json.loads(msg)
            if kind == "layer_plan":
                self.applied[int(d["layer"])] = (float(d["z_offset_mm"]), float(d["speed_factor"]))
            elif kind == "layer_count":
                self._set_count(int(d["layers"]))
            else:
                self.records.append(d)
                self.gain = float(d.get("gain") or self.gain)
                self.top = float(d["measured_top_mm"])
                self.expected_cum = float(d.get("expected_cum_mm") or 0.0)
                if d.get("source") in ("arc", "probe"):
                    self.hist.append((self.expected_cum, self.top))
                nxt = d.get("next") or {}
                self.next_dz = float(nxt.get("z_offset_mm", self.next_dz))
                self.next_k = float(nxt.get("speed_factor", self.next_k))
        if self.path is not None:
            self.path.restore()

    def adjust_work(self, work: list[WorkItem], done: set[tuple[int, int]]) -> list[WorkItem]:
        """The remaining work of the planned layers, without dropped layers, with added ones."""
        out = [w for w in work if w.layer < self.n_total]
        out += [WorkItem(j, pi) for j in range(self.n_planned, self.n_total)
                for pi in range(len(self.layers[j].passes)) if (j, pi) not in done]
        return out

    # -- the runner's layer source and hooks (controller/runtime/hooks.py) ------------------------
    def layer_count(self) -> int:
        return len(self.layers)

    def passes_in(self, i: int) -> int:
        return len(self.layers[i].passes)

    def layer(self, la: int) -> Layer:
        """Layer `la` as built (its z offset and trim journaled before its first bead)."""
        if not self.closed:
            return self.layers[la]
        got = self._built.get(la)
        if got is not None:
            return got
        if la not in self.applied:   # rounded as journaled: a resume lays it at the very same z
            dz, k = round(self.next_dz, 6), round(self.next_k, 6)
            self.applied[la] = (dz, k)
            self._event("layer_plan", {"layer": la, "z_offset_mm": dz, "speed_factor": k}, layer=la)
        dz, k = self.applied[la]
        if self.path is not None and self.path.keeps_width:   # the trim's rise laid as the path loop lays its own
            got = self.path.apply(la, adjusted_layer(self.layers[la], dz, 1.0), rise_factor(k, self.p))
        else:
            got = adjusted_layer(self.layers[la], dz, k)
            got = self.path.apply(la, got) if self.path is not None else got
        self._built[la] = got
        if self.bus is not None:
            self.bus.update(z_correction_mm=dz)
            if self.path is not None:
                f = [v for fs in self.path.applied.get(la, {}).values() for v in fs] or [1.0]
                self.bus.update(path_factor_min=min(f), path_factor_max=max(f))
        return got

    def pass_for(self, la: int, pa: int) -> Pass:
        return self.layer(la).passes[pa]

    async def before_motion(self) -> None:
        if self.prepare is not None:
            await self.prepare()

    def arc_sample(self, layer: int, pass_: int, along_mm: float, current_a: float,
                   wfs_m_min: float | None = None) -> None:
        """The runner's hook: the source's current at the robot's reported position along the pass."""
        if self.path is not None:
            self.path.arc_sample(layer, pass_, along_mm, current_a, wfs_m_min)

    def bead_closed(self, la: int, pa: int, currents: Sequence[float], wfs_m_min: float) -> None:
        """A bead's arc-stable current samples: its stick-out through the arc (journaled)."""
        e = self.est.estimate(currents, wfs_m_min)
        if e is None:
            return
        self.beads.setdefault(la, []).append(e)
        self._event("stick_out", {"layer": la, "pass": pa, "stick_out_mm": _r(e.stick_out_mm),
                                  "current_a": _r(e.current_a, 3), "n": e.n, "sigma_mm": _r(e.sigma_mm)}, layer=la)
        if self.bus is not None:
            self.bus.update(stick_out_mm=e.stick_out_mm)

    async def after_pass(self, item: WorkItem, rest: Sequence[WorkItem]) -> AfterPass:
        """After each pass: at the end of a layer (`rest` goes on with another), close it."""
        if rest and rest[0].layer == item.layer:
            return GO_ON
        return await self.layer_done(item.layer)

    # -- a layer's end ------------------------------------------------------------------------------
    async def _measure(self, la: int, z_cmd: float) -> tuple[float | None, str, float | None, list[float]]:
        """(top, source, stick-out, per-point stick-outs) of a layer just laid."""
        beads = self.beads.pop(la, [])
        if self.platform == "robot" and self.path is not None and self.path.wfs_varies(la):
            # the path loop laid some of it at another wire feed: each bin read at its own (a bead's
            # estimate reads the whole bead at its mean wire feed)
            rows = self._rows[la] = self.path.arc_tops(la, self.layer(la), z_cmd)
            if rows:
                top = float(np.mean([r[2] for r in rows]))
                return top, "arc", z_cmd + self.l0 - top, list(self.path.pass_stick_outs)
        if self.platform == "robot" and beads:
            vals = [b.stick_out_mm for b in beads]
            so = sum(vals) / len(vals)
            return z_cmd + self.l0 - so, "arc", so, vals
        last = la + 1 >= self.n_total
        if self.closed and self.probe is not None and ((la + 1) % self.cfg.probe_every_layers == 0 or last):
            spots = self._spots(la)
            t0 = time.monotonic()
            tops = await self.probe(la, spots)
            self.probe_s[la] = time.monotonic() - t0     # the probing's share of the build (the record)
            self._probed[la] = (spots, tops)
            if tops:
                vals = [z_cmd + self.l0 - t for t in tops]
                top = sum(tops) / len(tops)
                return top, "probe", z_cmd + self.l0 - top, vals
        return None, "model", None, []

    def _spots(self, la: int) -> list[Spot]:
        """Where the CNC probes layer la: along every pass (path loop), else a few spots."""
        if self.path is not None:
            return self.path.probe_spots(self.layer(la))
        return [(float(x), float(y), float(z)) for x, y, z in probe_spots(self.layer(la).passes, self.cfg.probe_points)]

    async def layer_done(self, la: int) -> AfterPass:
        """Layer la was laid: measure, record, decide the next layers; pause or go on, and the
        work after it when layers were added or dropped."""
        dz, kf = self.applied.get(la, (0.0, 1.0))
        z_cmd = layer_z(self.layers[la]) + dz
        planned = self.replanned_z(la)
        h = layer_height(self.layers[la])
        expected = h * rise_factor(kf, self.p)
        top, source, so, vals = await self._measure(la, z_cmd)
        self.expected_cum += expected
        if top is None:
            top = self.top + self.gain * expected
        else:
            self.hist.append((self.expected_cum, top))
            self.gain = fit_gain(self.hist, self.cfg.gain_window_layers) or self.gain
        self.top = top
        rec: dict[str, Any] = {
            "layer": la, "planned_top_mm": _r(planned), "z_mm": _r(z_cmd), "measured_top_mm": _r(top),
            "source": source, "stick_out_mm": _r(so), "stick_out_min_mm": _r(min(vals)) if vals else None,
            "stick_out_max_mm": _r(max(vals)) if vals else None, "height_error_mm": _r(top - planned),
            "z_offset_mm": _r(dz), "correction_mm": _r(z_cmd - planned), "speed_factor": _r(kf, 5), "gain": _r(self.gain, 5),
            "expected_rise_mm": _r(expected), "expected_cum_mm": _r(self.expected_cum), "mode": self.cfg.mode,
            "added": bool(self.layers[la].extra.get("added")),
        }
        if la in self.probe_s:
            rec["probe_s"] = _r(self.probe_s[la], 3)
        pause, rest = None, None
        if self.closed:
            rec["next"], rec["action"], pause, rest = self._next(la, top, so, vals)
        if self.path is not None:
            pause = self._path_close(la, z_cmd, planned, rec) or pause
        elif source == "model":
            return AfterPass(rest=rest)   # no measurement: nothing to record
        self.records.append(rec)
        self._event("layer", rec, layer=la)
        if self.bus is not None:
            self.bus.update(stick_out_mm=so, layer_height_error_mm=top - planned)
        return AfterPass(pause=pause, rest=rest)

    def _path_close(self, la: int, z_cmd: float, planned: float, rec: dict[str, Any]) -> str | None:
        """The path loop after layer la: its tops along every pass, learned; a pause message or None."""
        assert self.path is not None
        built = self.layer(la)
        probed = self._probed.pop(la, None)
        if probed:
            rows = self.path.probe_rows(la, built, *probed)
        elif la in self._rows:   # read already (the layer's top from its bins)
            rows = self._rows.pop(la)
        else:   # the robot's bins through the arc; a CNC layer not probed teaches nothing
            rows = self.path.arc_tops(la, built, z_cmd) if self.platform == "robot" else []
        nxt = self.layers[la + 1] if la + 1 < self.n_total else None
        rise = self.gain * layer_height(nxt or self.layers[la]) * rise_factor(self.next_k, self.p)
        prec, pause = self.path.close(la, rows, planned, rise, nxt)
        if prec is not None:
            rec["path_rms_mm"], rec["path_spread_mm"] = prec["rms_mm"], prec["spread_mm"]
        return pause

    def replanned_z(self, j: int) -> float:
        """Layer j's top in the current plan: the planned final top spread over the current layer
        count in proportion to the layers' heights (the job's z while no layer is added or dropped)."""
        hs = [layer_height(x) for x in self.layers]
        base = layer_z(self.job_layers[0]) - layer_height(self.job_layers[0])
        if len(hs) == self.n_planned or sum(hs) <= 0:
            return layer_z(self.layers[j])
        return base + (self.final_mm - base) * sum(hs[:j + 1]) / sum(hs)

    def _next(self, la: int, top: float, so: float | None,
              vals: list[float]) -> tuple[dict[str, Any], str, str | None, list[WorkItem] | None]:
        """The next layer's z and trim, the layer count; (record, action, pause, the work after
        layer la when the count changed)."""
        n_max = self.n_planned + math.ceil(self.n_planned * self.cfg.max_layer_change_pct / 100.0)
        heights = [layer_height(x) for x in build_layers(self.job_layers, max(self.n_total + 1, self.n_planned))]
        d = decide(top_mm=top, final_mm=self.final_mm, heights=heights, gain=self.gain, p=self.p,
                   k_range=self.k_range, n_done=la + 1, n_total=self.n_total, n_planned=self.n_planned,
                   layer_change=self.cfg.layer_change == "add_drop",
                   n_range=(self.n_planned - (n_max - self.n_planned), n_max))
        rest = None
        if d.n_total != self.n_total:
            self._set_count(d.n_total)
            rest = [WorkItem(j, pi) for j in range(la + 1, self.n_total) for pi in range(len(self.layers[j].passes))]
            self._event("layer_count", {"after_layer": la, "layers": self.n_total}, layer=la)
        self.next_k = self._catch_up(la, top, d.speed_factor)
        pause, corr = None, 0.0
        rise = self.gain * layer_height(self.layers[min(la + 1, self.n_total - 1)]) * rise_factor(self.next_k, self.p)
        # the layers the saturated trim needs to reach the planned top: beyond the allowed change,
        # the disturbance cannot be corrected in range (judged once the gain rests on enough layers)
        most = self.gain * layer_height(self.job_layers[-1]) * rise_factor(self.k_range[0], self.p)
        need = la + 1 + math.ceil(max(self.final_mm - top - 0.5 * most, 0.0) / most) if most > 0 else n_max
        if len(self.hist) > self.cfg.gain_window_layers and need > n_max and self.cfg.layer_change == "add_drop":
            pause = (f"layer {la + 1}: the part rises {self.gain:.2f} × the model a layer (top {top:.2f} mm after layer "
                     f"{la}, planned {self.replanned_z(la):.2f} mm); even at the speed trim's limit it needs {need} "
                     f"layers for the planned {self.final_mm:.2f} mm, beyond {n_max} "
                     f"(process_control.max_layer_change_pct {self.cfg.max_layer_change_pct:g})")
        if la + 1 < self.n_total:
            nxt = self.layers[la + 1]
            plan = self.replanned_z(la + 1)
            lim = self.cfg.max_z_correction_mm
            want = top + rise - plan
            corr = max(-lim, min(lim, want))
            self.next_dz = plan + corr - layer_z(nxt)
            if abs(want) > lim:
                pause = (f"layer {la + 1}: the part's top is {top - self.replanned_z(la):+.2f} mm off the plan "
                         f"after layer {la}; the next layer needs a z correction of {want:+.2f} mm, beyond "
                         f"process_control.max_z_correction_mm {lim:g}: its stick-out would be "
                         f"{self.l0 + want - corr:.2f} mm at the largest correction")
        lo, hi = self.cfg.ctwd_window_mm
        out = [v for v in vals if not lo <= v <= hi]
        if out:
            worst = max(out, key=lambda v: abs(v - self.l0))
            pause = (f"layer {la}: stick-out {worst:.2f} mm ({'through the arc' if self.platform == 'robot' else 'probed'}"
                     f", layer mean {so:.2f} mm) outside process_control.ctwd_window_mm [{lo:g}, {hi:g}]; "
                     f"paused before layer {la + 1}")
        nxt_rec = {"z_offset_mm": _r(self.next_dz), "correction_mm": _r(corr), "speed_factor": _r(self.next_k, 5),
                   "layers": self.n_total, "projected_top_mm": _r(d.projected_top_mm)}
        return nxt_rec, d.action, pause, rest

    def _catch_up(self, la: int, top: float, k: float) -> float:
        """The next layer's trim: aimed at the current plan's top `catch_up_layers` on (path mode's
        default 2: the path loop is judged layer by layer), else `k`, the trim that ends the build on
        its planned top (spread over the remaining layers, the layer loop's default)."""
        n = self.cfg.catch_up_layers or (2 if self.cfg.mode == "path" else 0)
        if not n or la + 1 >= self.n_total:
            return k
        j = min(la + n, self.n_total - 1)
        s = sum(layer_height(self.layers[i]) for i in range(la + 1, j + 1))
        if s <= 0.0 or self.gain <= 0.0:
            return k
        f = (self.replanned_z(j) - top) / (self.gain * s)
        lo, hi = self.k_range
        return min(max(speed_for(f, self.p), lo), hi) if f > 0.0 else hi

    def _set_count(self, n: int) -> None:
        self.n_total = n
        self.layers[:] = build_layers(self.job_layers, n)
        for j in [j for j in self._built if j >= n]:
            del self._built[j]
        if self.bus is not None:
            self.bus.update(layers_total=n, passes_total=sum(len(x.passes) for x in self.layers))


def make_control(cfg: CellConfig, job: CellJob, material: Material, journal: Journal, bus: EventBus | None,
                 executor: MotionExecutor) -> LayerControl:
    """The build's layer control (restored from the journal on a resume); the CNC's probe when it has one."""
    pc = cfg.process_control
    probe: ProbeFn | None = None
    link = executor.cnc_link

    async def homed() -> None:   # before the first layer, not after it over a fresh bead (nor in the probing's time)
        assert link is not None
        if not link.homed:
            await home(link)
    prepare = homed if link is not None and pc.mode in ("layer", "path") else None
    if link is not None and pc.mode == "path":
        # the path loop's points along every pass: one touch each, three lines a point sent together, from just
        # above the layer's top (controller/runtime/path_probe.py; docs/closed-loop.md)
        hop = min(cfg.probe.clearance_mm, PATH_PROBE_CLEARANCE_MM)
        plan = TouchPlan(hop_mm=hop, depth_mm=max(cfg.probe.travel_mm - hop, hop),
                         touch_feed=max(cfg.probe.fast_feed_mm_min, PATH_PROBE_FEED_MM_MIN))

        seen: list[tuple[list[Spot], list[float]]] = []   # the layer probed before: its spots and tops
        miss = [0.0]    # how far a top stood above plan and expectation on the layer probed before: the travel clears it too

        async def touch(la: int, spots: Sequence[Spot]) -> list[float]:
            assert link is not None
            exp = expected_tops(*seen[-1], list(spots)) if seen else [z for _, _, z in spots]
            hop = replace(plan, hop_mm=plan.hop_mm + min(miss[0], PATH_PROBE_MAX_EXTRA_HOP_MM))
            tops = await touch_tops(link, list(spots), hop, name=f"layer {la} top", expect=exp)
            seen[:] = [(list(spots), tops)]
            # a top above what the travel cleared it by (the higher of its plan and its expectation; one below is no threat)
            miss[0] = max((t - max(e, s[2]) for t, e, s in zip(tops, exp, spots)), default=0.0)
            return tops
        probe = touch
    elif link is not None:
        async def probe_top(la: int, spots: Sequence[Spot]) -> list[float]:
            assert link is not None
            return await probe_layer_top(link, cfg.probe, list(spots), cfg.probe.clearance_mm, name=f"layer {la} top")
        probe = probe_top
    lc = LayerControl(job=job, cfg=pc, material=material, platform=cfg.cell.platform, journal=journal, bus=bus,
                      max_speed_mm_min=cfg.limits.max_speed_mm_min, probe=probe, prepare=prepare)
    lc.restore()
    return lc
