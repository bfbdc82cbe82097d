"""The path loop (`process_control: {mode: path}`, docs/closed-loop.md "Along the path"): the
layer loop's mean z and trim, plus a speed factor per segment learned from layer to layer by
position in the part (controller/runtime/path_plan.py, the pure half).

The layer control (layer_control.py) calls it at three points:
- `apply(la, layer)`: layer la as built gets its passes resampled (segments of at most half a
  bead width) and its per-segment speeds (`Pass.with_process`, cell-job/2) times the factors;
  the factors are journaled (`path_plan`) before the layer's first bead and read back on a resume,
  so a layer is laid with the same speeds after a restart; the job file is never rewritten;
- `arc_sample(la, pa, s, current)`: robot, the power source's current at the robot's reported
  position s along the pass (the runner's `arc_sample` hook);
- `close(...)`: after the layer, its tops along every pass (robot: the samples binned about one
  bead width, each bin's stick-out through the arc; CNC: the probe points given), the error
  fields, the next layer's factors and a pause message when a correction it needs is out of bounds.
"""
from __future__ import annotations

import json
from dataclasses import replace
from typing import Any, Sequence

import numpy as np

from controller.journal.store import Journal
from controller.runtime.events import EventBus
from controller.runtime.path_plan import (
    NO_CUTS, Field, PathLaw, arc_length, bin_samples, cut_polyline, plan_factors, point_at, process_for, resample, rise_ratio,
    spots_along, spread_reports,
)
from controller.runtime.path_edges import EdgeFinder
from controller.runtime.stickout import StickOutEstimator
from core.config import ProcessControl
from core.melting import stick_out_at
from planner.job import Layer, Pass
from planner.pour import BeadLaw

__all__ = ["PathControl"]


def _unit_rows(a: np.ndarray | None, idx: np.ndarray) -> np.ndarray | None:
    """Per-point unit vectors (normals, axes) at fractional indices: linear, renormalised."""
    if a is None:
        return None
    lo = np.floor(idx).astype(int)
    hi = np.minimum(lo + 1, len(a) - 1)
    f = (idx - lo)[:, None]
    v = a[lo] * (1.0 - f) + a[hi] * f
    n = np.linalg.norm(v, axis=1, keepdims=True)
    out: np.ndarray = v / np.where(n > 1e-12, n, 1.0)
    return out


class PathControl:
    """One build's path loop (the state between layers, its journal and its resume)."""

    def __init__(self, *, cfg: ProcessControl, journal: Journal, bus: EventBus | None, platform: str,
                 est: StickOutEstimator, width_mm: float, max_speed_mm_min: float = 1e9) -> None:
        self.cfg, self.journal, self.bus, self.platform, self.est = cfg, journal, bus, platform, est
        self.width = width_mm
        trim, wt = cfg.speed_trim_pct / 100.0, cfg.path_wfs_trim_pct / 100.0
        self.speed_bounds = cfg.path_speed_range or (max(1.0 - trim, 0.05), 1.0 + trim)
        self.wfs_bounds = (max(1.0 - wt, 0.05), 1.0 + wt)
        line = est.material.ribeiro
        self.wfs_envelope = (line.wfs_min_m_min, line.wfs_max_m_min)
        self.bead = BeadLaw(line.k1, line.k2, line.k3, line.i_min_a, line.i_max_a, line.wfs_min_m_min, line.wfs_max_m_min)
        # the law's factor is the metal's (speed over wire feed): the speed's bound, then the wire feed's
        self.law = PathLaw(kp=cfg.path_kp, ki=cfg.path_ki, filter_mm=max(cfg.path_filter_mm or 1.5 * width_mm, cfg.path_bin_mm or width_mm,
                                                                                 cfg.probe_spacing_mm if platform == "cnc" else 0.0),
                           bounds=(self.speed_bounds[0] / self.wfs_bounds[1], self.speed_bounds[1] / self.wfs_bounds[0]))
        self.max_speed = max_speed_mm_min
        self.spacing = width_mm / 2.0
        self.bin_mm = cfg.path_bin_mm or width_mm
        self.applied: dict[int, dict[int, list[float]]] = {}       # the metal factor (speed / wire feed) per segment
        self.applied_wfs: dict[int, dict[int, list[float]]] = {}   # the wire feed's share of it
        self.samples: dict[tuple[int, int], list[tuple[float, float, float]]] = {}   # (s, current, feed or NaN)
        self.fields: list[tuple[Field, Field]] = []     # (d, m) of the last measured layers, newest last
        self.records: list[dict[str, Any]] = []
        self.rise_mm = 0.0
        self._rise = 1.0     # the layer loop's trim as a rise factor, of the layer last applied
        self._bad = np.zeros((0, 2))    # where the last layer needed a correction beyond the bound
        self.pass_stick_outs: list[float] = []   # per pass of the last `arc_tops`: its stick-out
        self.edges = EdgeFinder(width_mm=width_mm)    # the hidden regions' edges, found along the passes
        self.cuts_at: dict[int, np.ndarray] = {}       # the cuts (x y ux uy) each layer was laid with

    # -- journal --------------------------------------------------------------------------------
    def _event(self, kind: str, data: dict[str, Any], layer: int) -> None:
        self.journal.event(kind, json.dumps(data, sort_keys=True), layer=layer)

    def restore(self) -> None:
        """A resumed build: the factors applied and the latest fields, from the journal."""
        for kind, msg in self.journal.query("SELECT kind, message FROM events WHERE kind IN "
                                            "('path_plan', 'path') ORDER BY id"):
            d = json.loads(msg)
            if kind == "path_plan":
                self.applied[int(d["layer"])] = {int(k): [float(x) for x in v] for k, v in d["factors"].items()}
                self.applied_wfs[int(d["layer"])] = {int(k): [float(x) for x in v] for k, v in (d.get("wfs") or {}).items()}
                self.cuts_at[int(d["layer"])] = np.asarray(d.get("cuts") or [], dtype=float).reshape(-1, 4)
                self.edges.cuts = self.cuts_at[int(d["layer"])]
                self.edges.forget_misses()
            else:
                self.records.append(d)
                self.rise_mm = float(d.get("rise_mm") or self.rise_mm)
                self.fields = (self.fields + [(Field.of(d["d"]), Field.of(d["m"]))])[-2:]

    # -- the layer as built -----------------------------------------------------------------------
    def _resampled(self, p: Pass, cuts: np.ndarray = NO_CUTS) -> tuple[Pass, np.ndarray]:
        """The pass with segments of at most `spacing`, split where it crosses a region's edge (`cuts`)
        (its per-segment values carried over); the original segment of every new one."""
        pts, idx = cut_polyline(*resample(p.points, self.spacing), cuts)
        seg = np.maximum(np.ceil(idx[1:] - 1e-9).astype(int) - 1, 0)
        speeds, wfs = p.speeds()[seg], p.wire_feeds()[seg]
        q = replace(p, points=pts, normals=_unit_rows(p.normals, idx), axes=_unit_rows(p.axes, idx),
                    speed_mm_min=p.speed_mm_min, seg_speed_mm_min=None, seg_wfs_m_min=None)
        return q.with_process(speeds, wfs if p.seg_wfs_m_min is not None else None), seg

    def _plan(self, la: int, passes: Sequence[Pass], cuts: np.ndarray = NO_CUTS) -> tuple[dict[int, list[float]], np.ndarray, np.ndarray, np.ndarray]:
        """(factors per pass, all needed factors, all midpoints, all d there) of a layer from the fields."""
        mids = [0.5 * (p.points[1:, :2] + p.points[:-1, :2]) for p in passes]
        lens = [np.hypot(*np.diff(p.points[:, :2], axis=0).T) for p in passes]
        if not self.fields or not passes:
            return {pa: [1.0] * len(m) for pa, m in enumerate(mids)}, np.ones(0), np.zeros((0, 2)), np.zeros(0)
        d_now, m_now = self.fields[-1]
        d_prev = self.fields[-2][0] if len(self.fields) > 1 else None
        xy, ln = np.concatenate(mids), np.concatenate(lens)
        self.law = replace(self.law, bounds=self.bounds(passes, self._rise))
        got, need = plan_factors(xy, ln, d_now, d_prev, m_now, self.rise_mm, self.law, cuts)
        if not self.cfg.path_wfs_trim_pct:
            top_speed = max(float(p.speeds().max()) for p in passes)
            got = np.minimum(got, max(self.max_speed / top_speed, 1e-3))
        out, k = {}, 0
        for pa, m in enumerate(mids):
            out[pa] = [round(float(v), 5) for v in got[k:k + len(m)]]
            k += len(m)
        return out, need, xy, d_now.at(xy, self.law.filter_mm / 4.0, self.law.filter_mm, cuts)

    def _limits(self, speeds: np.ndarray, wfs: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """Per segment: the speed's (lo, hi) and the wire feed's (lo, hi), absolute."""
        lo, hi = self.speed_bounds
        v = (speeds * lo, np.minimum(speeds * hi, np.maximum(self.max_speed, speeds)))
        f = (np.clip(wfs * self.wfs_bounds[0], *self.wfs_envelope), np.clip(wfs * self.wfs_bounds[1], *self.wfs_envelope))
        return v, (np.minimum(f[0], wfs), np.maximum(f[1], wfs))

    def bounds(self, passes: Sequence[Pass], rise: float = 1.0) -> tuple[float, float]:
        """The law's bounds on m: the speed's alone, or with the wire feed the rise's reach (m = 1/rise)
        over the layer's segments, the layer loop's trim (`rise`) laid on top."""
        if not self.cfg.path_wfs_trim_pct or not passes:
            return self.speed_bounds
        v0 = np.concatenate([p.speeds() for p in passes])
        f0 = np.concatenate([p.wire_feeds() for p in passes])
        (vlo, vhi), (flo, fhi) = self._limits(v0, f0)
        most = rise_ratio(self.bead, vlo, flo, v0, f0)
        least = rise_ratio(self.bead, vhi, fhi, v0, f0)
        return float(rise / most.min()), float(rise / least.max())

    def split(self, m: np.ndarray, speeds: np.ndarray, wfs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The path factor m per segment as (speed factor, wire feed factor). Without the wire feed:
        the speed within its bound and the cell's top speed. With it, m is the rise's inverse: the
        speed and wire feed that lay 1/m × the rise keeping the bead's width (path_plan.process_for)."""
        vb, fb = self._limits(speeds, wfs)
        if not self.cfg.path_wfs_trim_pct:
            sp = np.clip(m, self.speed_bounds[0], vb[1] / np.maximum(speeds, 1e-9))
            return sp, np.ones(len(m))
        v, f = process_for(1.0 / np.maximum(m, 1e-6), speeds, wfs, self.bead, vb, fb)
        f = f / np.maximum(wfs, 1e-9)
        return v / np.maximum(speeds, 1e-9), np.where(np.abs(f - 1.0) < 1e-4, 1.0, f)

    @property
    def keeps_width(self) -> bool:
        """Speed and wire feed set together (the wire feed in play): the layer loop's trim is laid
        the same way (`apply`'s `rise`), so the rise follows the metal as the layer loop models it."""
        return self.cfg.path_wfs_trim_pct > 0.0

    def apply(self, la: int, layer: Layer, rise: float = 1.0) -> Layer:
        """Layer la as built: resampled, its segment speeds (and wire feeds, `keeps_width`) set by
        the path factors (journaled before its first bead); `rise`: the layer loop's trim as a rise
        factor (with `keeps_width`; else the layer comes trimmed)."""
        if la not in self.applied:
            self.cuts_at[la] = self.edges.cuts
        cuts = self.cuts_at.get(la, NO_CUTS)
        passes = [self._resampled(p, cuts)[0] for p in layer.passes]
        self._rise = rise
        if la not in self.applied:
            self.applied[la] = self._plan(la, passes, cuts)[0]
            self.applied_wfs[la] = {}
            for pa, p in enumerate(passes):
                m = np.asarray(self.applied[la].get(pa, []), dtype=float)
                if len(m) == len(p.points) - 1:
                    _, f = self.split(m / rise, p.speeds(), p.wire_feeds())
                    if np.any(f != 1.0):
                        self.applied_wfs[la][pa] = [round(float(v), 5) for v in f]
            self._event("path_plan", {"layer": la, "spacing_mm": self.spacing,
                                      "factors": {str(k): v for k, v in self.applied[la].items()},
                                      "wfs": {str(k): v for k, v in self.applied_wfs[la].items()},
                                      "cuts": [[round(float(v), 4) for v in c] for c in cuts]}, la)
        out = []
        for pa, p in enumerate(passes):
            m = np.asarray(self.applied[la].get(pa, []), dtype=float)
            if len(m) != len(p.points) - 1:   # a pass the journal did not see (never: same geometry)
                m = np.ones(len(p.points) - 1)
            sp, f = self.split(m / rise, p.speeds(), p.wire_feeds())
            out.append(p.with_process(p.speeds() * sp, p.wire_feeds() * f if np.any(f != 1.0) else None))
        return replace(layer, passes=tuple(out))

    def wfs_varies(self, la: int) -> bool:
        """Does layer la lay any segment at another wire feed than planned (the path loop's)?"""
        return bool(self.applied_wfs.get(la))

    # -- sensing ------------------------------------------------------------------------------------
    def arc_sample(self, la: int, pa: int, s_mm: float, current_a: float, wfs_m_min: float | None = None) -> None:
        self.samples.setdefault((la, pa), []).append((s_mm, current_a, float("nan") if wfs_m_min is None else wfs_m_min))

    def _stick_outs(self, la: int, pa: int, p: Pass, cum: np.ndarray) -> list[tuple[float, float]]:
        """The pass's samples as (s, stick-out): each current read at the wire feed the source
        reported with it (a feed the source had not reached yet read at the plan's would be off by
        mm: 4 A/mm against ~19 A per m/min of feed), else at the plan's feed of the move there."""
        out, line, wf = [], self.est.material.ribeiro, p.wire_feeds()
        for s, cur, f in self.samples.pop((la, pa), []):
            if not np.isfinite(f) or f <= 0.0:
                f = float(wf[min(max(int(np.searchsorted(cum, s, side="right")) - 1, 0), len(cum) - 2)])
            out.append((s, stick_out_at(self.est.rel, line, f, cur)))
        return out

    def arc_tops(self, la: int, layer: Layer, z_cmd: float) -> list[tuple[float, float, float, float]]:
        """Robot: (x, y, top, factor) per bin of about one bead width along every pass of the layer
        as built, from the current binned by the robot's reported position."""
        rows: list[tuple[float, float, float, float]] = []
        self.pass_stick_outs = []
        for pa, p in enumerate(layer.passes):
            n0 = len(rows)
            cum = arc_length(p.points)
            fac = self.applied.get(la, {}).get(pa, [])
            # the first half width of a bead: the pool not yet risen under the torch (it reads the ground)
            got = [(s, L) for s, L in spread_reports(self._stick_outs(la, pa, p, cum), float(cum[-1])) if s >= self.width / 2.0]
            v, f = p.speeds(), p.wire_feeds()   # the metal each segment was laid with, as the bead law has it
            if self.cfg.path_edges:
                self.edges.add(la, pa, p.points, cum, [(s, z_cmd + self.est.nominal_mm - L) for s, L in got],
                               1.0 / rise_ratio(self.bead, v, f, np.full(len(v), v[0]), np.full(len(f), f[0])))
            breaks = self.edges.breaks(p.points, cum, self.cuts_at.get(la, NO_CUTS))
            for s, L, _n in bin_samples(got, float(cum[-1]), self.bin_mm, breaks=breaks):
                k = min(max(int(np.searchsorted(cum, s, side="right")) - 1, 0), len(cum) - 2)
                x, y = point_at(p.points, cum, s)[:2]
                rows.append((float(x), float(y), z_cmd + self.est.nominal_mm - L, fac[k] if k < len(fac) else 1.0))
            if len(rows) > n0:   # the bead's stick-out: its bins' median (a wall's end bin is one of them)
                self.pass_stick_outs.append(float(np.median([z_cmd + self.est.nominal_mm - r[2] for r in rows[n0:]])))
        return rows

    def probe_spots(self, layer: Layer) -> list[tuple[float, float, float]]:
        """CNC: probe spots along every pass at `probe_spacing_mm` (the ends a quarter width in)."""
        out = []
        for p in layer.passes:
            for q in spots_along(p.points, self.cfg.probe_spacing_mm, self.width / 4.0):
                out.append((float(q[0]), float(q[1]), float(q[2])))
        return out

    def probe_rows(self, la: int, layer: Layer, spots: Sequence[tuple[float, float, float]],
                   tops: Sequence[float]) -> list[tuple[float, float, float, float]]:
        """CNC: (x, y, top, factor) per probed spot (the factor of the nearest segment)."""
        f_all = [(0.5 * (p.points[1:, :2] + p.points[:-1, :2]), np.asarray(self.applied.get(la, {}).get(pa, [1.0] * (len(p.points) - 1))))
                 for pa, p in enumerate(layer.passes)]
        mids = np.concatenate([m for m, _ in f_all]) if f_all else np.zeros((0, 2))
        facs = np.concatenate([f for _, f in f_all]) if f_all else np.zeros(0)
        rows = []
        for (x, y, _z), t in zip(spots, tops):
            k = int(np.argmin(np.hypot(mids[:, 0] - x, mids[:, 1] - y))) if len(mids) else -1
            rows.append((x, y, float(t), float(facs[k]) if k >= 0 and k < len(facs) else 1.0))
        return rows

    # -- a layer's end -----------------------------------------------------------------------------
    def close(self, la: int, rows: Sequence[tuple[float, float, float, float]], planned_top: float,
              rise_mm: float, next_layer: Layer | None) -> tuple[dict[str, Any] | None, str | None]:
        """Record layer la's tops along the path, learn, and say whether the next layer's needed
        correction is out of bounds (a pause message)."""
        if not rows:
            return None, None
        a = np.asarray(rows, dtype=float)
        mean = float(a[:, 2].mean())
        err = a[:, 2] - planned_top
        d = Field(a[:, :2].copy(), a[:, 2] - mean)
        m = Field(a[:, :2].copy(), a[:, 3].copy())
        self.fields = (self.fields + [(d, m)])[-2:]
        self.rise_mm = rise_mm
        rec: dict[str, Any] = {
            "layer": la, "planned_top_mm": round(planned_top, 4), "mean_top_mm": round(mean, 4),
            "rms_mm": round(float(np.sqrt(np.mean(err ** 2))), 4),
            "shape_rms_mm": round(float(np.sqrt(np.mean(d.v ** 2))), 4),
            "spread_mm": round(float(a[:, 2].max() - a[:, 2].min()), 4), "rise_mm": round(rise_mm, 4),
            "d": d.rows(), "m": m.rows(5), "source": "arc" if self.platform == "robot" else "probe",
        }
        pause = None
        if next_layer is not None:
            if self.cfg.path_edges:
                self.edges.find(la)
            passes = [self._resampled(p, self.edges.cuts)[0] for p in next_layer.passes]
            _, need, xy, dn = self._plan(la + 1, passes, self.edges.cuts)
            lo, hi = self.law.bounds
            bad = ((need < lo - 1e-6) | (need > hi + 1e-6)) & (np.abs(np.nan_to_num(dn)) > self.cfg.path_max_error_mm)
            rec["needed_min"], rec["needed_max"] = (round(float(need.min()), 4), round(float(need.max()), 4)) if len(need) else (None, None)
            # out of bounds where it was already after the last layer: one layer's reading is not enough
            prev, self._bad = self._bad, xy[bad]
            if len(prev):
                near = np.hypot(xy[:, None, 0] - prev[None, :, 0], xy[:, None, 1] - prev[None, :, 1]).min(axis=1)
                bad &= near <= self.law.filter_mm
            else:
                bad &= False
            if np.any(bad):
                k = int(np.argmax(np.where(bad, np.abs(need - 1.0), -1.0)))
                pause = (f"layer {la + 1}: the top at x {xy[k, 0]:.1f}, y {xy[k, 1]:.1f} mm is {dn[k]:+.2f} mm off the "
                         f"layer's mean after layer {la}; levelling it needs {need[k]:.2f} × the speed there, beyond "
                         f"process_control.speed_trim_pct {self.cfg.speed_trim_pct:g} with path_wfs_trim_pct "
                         f"{self.cfg.path_wfs_trim_pct:g} (the path loop's bounds)")
        self.records.append(rec)
        self._event("path", rec, la)
        if self.bus is not None:
            self.bus.update(path_rms_mm=rec["rms_mm"], path_spread_mm=rec["spread_mm"])
        return rec, pause
