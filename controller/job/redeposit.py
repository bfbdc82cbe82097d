"""Deposit again where the stock probe found the deposit short (pure; docs/machining.md "Deposit again").

The short spots (CAD frame, each with its probed top and its height over CAD) become a small job
in the repair job's frame, built on the same alignment:
- spots closer than half a bead are one (the lowest kept);
- each spot one short pass, a bead's width long, inward (toward the region's middle) along the
  nearest segment of the job's top layer, starting `RUN_IN_MM` before the spot (a bead's start
  lays less metal): beads along the walls stay along them, and a corner spot gets a bead
  reaching into the corner the planned perimeter turned short of;
- layers: as many as the lowest spot needs to stand `target_mm` above CAD at the job's layer
  height (at most `max_layers`); a spot joins a layer while it still needs metal; layer k lies
  at the highest probed top + k layer heights (the torch's stick-out as planned);
- the passes' process (current, wire feed, width) is the top layer's, at its mean travel speed;
  the interpass wait too.
"""
from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from controller.job.model import CellJob
from controller.job.read import job_from_dict
from core.errors import InputError

F = NDArray[np.float64]


def _merge(pts: F, over: F, radius: float) -> tuple[F, F]:
    """Spots closer than `radius` are one: the lowest (least over CAD) kept."""
    order = np.argsort(over)
    keep: list[int] = []
    for i in order:
        if all(float(np.hypot(*(pts[i, :2] - pts[j, :2]))) >= radius for j in keep):
            keep.append(int(i))
    return pts[keep], over[keep]


def _along(top: list[F], xy: F) -> F:
    """The unit direction of the top layer's segment nearest to `xy` (+X when there is none)."""
    best, d_best = np.array([1.0, 0.0]), math.inf
    for p in top:
        a, b = p[:-1, :2], p[1:, :2]
        ab = b - a
        L2 = np.maximum((ab * ab).sum(axis=1), 1e-12)
        t = np.clip(((xy - a) * ab).sum(axis=1) / L2, 0.0, 1.0)
        d = np.hypot(*(a + t[:, None] * ab - xy).T)
        k = int(np.argmin(d))
        if d[k] < d_best and L2[k] > 1e-6:
            d_best, best = float(d[k]), ab[k] / math.sqrt(float(L2[k]))
    return best


RUN_IN_MM = 1.0   # a pass starts this far before its spot: its thin run-in lands beside the spot


def _pass(role_of: dict[str, Any], spot: F, along: F, length: float, z: float) -> dict[str, Any]:
    a = spot[:2] - RUN_IN_MM * along
    b = spot[:2] + (length - RUN_IN_MM) * along
    return {**role_of, "points": [[round(float(a[0]), 3), round(float(a[1]), 3), round(z, 4)],
                                  [round(float(b[0]), 3), round(float(b[1]), 3), round(z, 4)]]}


def _process(job: CellJob) -> tuple[dict[str, Any], float, float, list[F]]:
    """The top layer's process as one pass's fields, its bead width and layer height, its segments."""
    layers = sorted(job.layers, key=lambda L: L.z_mm)
    if not layers or not any(p.points.shape[0] >= 2 for p in layers[-1].passes):
        raise InputError("redeposit: the repair job has no top layer to take the process from")
    top = layers[-1]
    first = next(p for p in top.passes if p.points.shape[0] >= 2)
    width = float(first.width_mm or job.job.bead.width_mm)
    h = float(top.height_mm or job.job.bead.height_mm)
    speed = float(np.mean(first.seg_speed_mm_min)) if first.seg_speed_mm_min is not None else float(first.speed_mm_min)
    wfs = float(np.mean(first.seg_wfs_m_min)) if first.seg_wfs_m_min is not None else float(first.wfs_m_min)
    process = {"role": "infill", "width_mm": round(width, 3), "current_a": round(float(first.current_a), 2),
               "speed_mm_min": round(speed, 1), "wfs_m_min": round(wfs, 3)}
    return process, width, h, [q.points for q in top.passes if q.points.shape[0] >= 2]


MERGE_WIDTHS = 0.5    # spots closer than this many bead widths are one: a bead laid at one covers the other


def _shifted(layer: dict[str, Any], z: float, h: float) -> dict[str, Any]:
    """A copy of a planned layer (JSON) moved up to z (its passes' points with it)."""
    dz = z - float(layer["z_mm"])
    passes = [{**q, "points": [[pt[0], pt[1], round(float(pt[2]) + dz, 4), *pt[3:]] for pt in q["points"]]}
              for q in layer["passes"]]
    return {**{k: v for k, v in layer.items() if k not in ("passes", "z_mm", "height_mm", "index")},
            "z_mm": round(z, 4), "height_mm": round(h, 4), "passes": passes}


def _full_layers(obj: dict[str, Any], n: int, z0: float, h: float) -> list[dict[str, Any]]:
    """n whole layers over the region from z0 + h up: the plan's top two layers again, alternating
    as the plan did (the second-highest first), each at its own height over the surface measured."""
    planned = sorted(obj["layers"], key=lambda L: float(L["z_mm"]))
    planned = [L for L in planned if any(len(q["points"]) >= 2 for q in L["passes"])]
    tops = planned[-2:][::-1] if len(planned) >= 2 else planned[-1:]
    return [_shifted(tops[(k + 1) % len(tops)] if len(tops) == 2 else tops[0], z0 + (k + 1) * h, h) for k in range(n)]


def _spot_layers(job: CellJob, process: dict[str, Any], seg: list[F], p: F, o: F, width_h: tuple[float, float],
                 base: float, n_layers: int, target_mm: float) -> list[dict[str, Any]]:
    """Layers of short passes, one per spot still short (`o` its height over CAD), from base + h up."""
    width, h = width_h
    rb = job.repair.bounds_mm if job.repair is not None else None
    mid = np.asarray(rb, dtype=float)[:, :2].mean(axis=0) if rb is not None else p[:, :2].mean(axis=0)
    dirs = [_along(seg, q[:2]) for q in p]
    dirs = [d if float(np.dot(d, mid - q[:2])) >= 0 else -d for d, q in zip(dirs, p)]   # from the spot inward
    out: list[dict[str, Any]] = []
    for k in range(1, n_layers + 1):
        need = [i for i in range(len(p)) if o[i] + (k - 1) * h < target_mm]
        if not need:
            break
        z = base + k * h
        out.append({"z_mm": round(z, 4), "height_mm": round(h, 4),
                    "passes": [_pass(process, p[i], dirs[i], width, z) for i in need]})
    return out


def redeposit_job(job: CellJob, pts: F, over: F, target_mm: float, *, round_no: int = 1,
                  max_layers: int = 4, typical: tuple[float, float] | None = None) -> CellJob:
    """A job depositing again at the short spots `pts` ((n, 3) CAD frame, probed tops) whose
    heights over CAD are `over` (n,), until each stands `target_mm` over CAD.

    `typical`: the deposit's typical height over CAD and its typical z (the median of the stock
    probe's ring and grid touches). Where that itself is under the target, the whole region is
    short (a process laying less than planned): whole layers again (the plan's top layers, as
    many as the typical height needs, at most `max_layers`), then short passes where still short."""
    if not len(pts):
        raise InputError("redeposit: no short spot to deposit at")
    process, width, h, seg = _process(job)
    p, o = _merge(np.asarray(pts, dtype=float), np.asarray(over, dtype=float), MERGE_WIDTHS * width)
    obj = json.loads(job.json)
    n_full = 0
    if typical is not None and typical[0] < target_mm:
        n_full = int(min(max_layers, math.ceil((target_mm - typical[0]) / h)))
    out_layers = _full_layers(obj, n_full, typical[1], h) if typical is not None and n_full else []
    o = o + n_full * h
    n_layers = int(min(max_layers - n_full, max(0, math.ceil((target_mm - float(o.min())) / h))))
    # over the highest short spot, and over the deposit around them (a spot in a hole: the torch at the
    # surroundings' height, the bead's pool fills the hole)
    base = max(float(p[:, 2].max()), float(typical[1]) + n_full * h if typical is not None else -math.inf)
    out_layers += _spot_layers(job, process, seg, p, o, (width, h), base, n_layers, target_mm)
    interpass = next((L.get("interpass") for L in reversed(obj["layers"]) if L.get("interpass")), None)
    for i, layer in enumerate(out_layers):
        layer["index"] = i
        layer.pop("interpass", None)
        if interpass is not None and i:
            layer["interpass"] = interpass
    obj["layers"] = out_layers
    obj["name"] = f"{job.name}-redeposit{round_no}"
    obj["summary"] = {"redeposit": {"round": round_no, "spots": len(p), "layers": len(out_layers),
                                    "whole_layers": n_full, "target_mm": target_mm}}
    return job_from_dict(obj, f"the redeposit job of {job.name}")
