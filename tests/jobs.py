"""Small jobs for tests, built from the planner's typed job (planner/job.py), not from hand-written dicts.

    job = small_job([[PassSpec(square(20.0), speed=[600, 600, 450, 600])]])      # a CellJob
    obj = job_object([[PassSpec(line(30.0), wfs=[5.5, 6.0, 6.5])]])            # its file's object

A pass's `speed` / `wfs` is one number, or one per segment (segment i from point i to i + 1):
any list makes the job `cell-job/2`, as the writer decides.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from controller.job.model import CellJob
from controller.job.read import job_from_dict
from planner.job import BeadInfo, Interpass, Job, Layer, Pass, Source, job_to_json

Point = tuple[float, float, float]


@dataclass(frozen=True)
class PassSpec:
    """One bead of a small job: its points (z is the layer's top unless given) and its process."""

    points: Sequence[Sequence[float]]
    speed: float | Sequence[float] = 600.0
    wfs: float | Sequence[float] = 5.5
    current: float = 120.0
    width: float = 5.0
    role: str = "perimeter"
    normals: Sequence[Sequence[float]] | None = None   # one facet normal per point (perimeters)
    axes: Sequence[Sequence[float]] | None = None      # one tool axis per point (5-axis)


@dataclass(frozen=True)
class JobSpec:
    material: str = "inconel718-1.0mm"
    layer_height: float = 1.0
    width: float = 5.0
    step_over: float = 3.69
    dwell_s: float | None = None
    name: str = "small"
    extra: dict[str, Any] = field(default_factory=dict)
    frame: str = "substrate"          # "cad": the points are the CAD's (a repair job)
    first_z: float | None = None      # layer 0's top (else one layer height); layer k's is k heights above
    model: str = "tangent"


def square(side: float, x0: float = 0.0, y0: float = 0.0, gap: float = 0.5) -> list[list[float]]:
    """A square loop, open by `gap` mm at its start (a perimeter bead)."""
    return [[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side], [x0, y0 + gap]]


def line(length: float, x0: float = 0.0, y0: float = 0.0, n: int = 2) -> list[list[float]]:
    """A straight bead along +x, cut into n - 1 segments."""
    return [[x0 + length * k / (n - 1), y0] for k in range(n)]


def _pass(spec: PassSpec, z: float) -> Pass:
    pts = np.array([[float(q[0]), float(q[1]), float(q[2]) if len(q) > 2 else z] for q in spec.points])
    one_speed = isinstance(spec.speed, (int, float))
    one_wfs = isinstance(spec.wfs, (int, float))
    p = Pass(spec.role, spec.width, spec.current, float(spec.speed) if one_speed else 1.0,
             float(spec.wfs) if one_wfs else 1.0, pts,
             None if spec.normals is None else np.asarray(spec.normals, dtype=float),
             None if spec.axes is None else np.asarray(spec.axes, dtype=float))
    return p.with_process(None if one_speed else np.asarray(spec.speed, dtype=float),
                          None if one_wfs else np.asarray(spec.wfs, dtype=float))


def planner_job(layers: Sequence[Sequence[PassSpec]], spec: JobSpec = JobSpec()) -> Job:
    """The planner's typed job of `layers` (layer k's top at (k + 1) × layer height)."""
    out = []
    for li, passes in enumerate(layers):
        z = (spec.layer_height if spec.first_z is None else spec.first_z) + spec.layer_height * li
        ip = Interpass(200.0, spec.dwell_s) if spec.dwell_s is not None else None
        out.append(Layer(li, z, spec.layer_height, tuple(_pass(p, z) for p in passes), ip))
    return Job(Source(f"{spec.name}.stl", "0" * 64, "mm"), {"name": spec.material},
               BeadInfo(spec.width, spec.layer_height, spec.step_over, spec.model), tuple(out), dict(spec.extra),
               frame=spec.frame)


def job_object(layers: Sequence[Sequence[PassSpec]], spec: JobSpec = JobSpec()) -> dict[str, Any]:
    """The file's object (what `cell plan` would write) of a small job."""
    obj: dict[str, Any] = json.loads(job_to_json(planner_job(layers, spec)))
    return obj


def small_job(layers: Sequence[Sequence[PassSpec]], spec: JobSpec = JobSpec()) -> CellJob:
    """A small job read as a file's (controller/job/read.py): what `cell run` would carry."""
    return job_from_dict(job_object(layers, spec), f"{spec.name}.json")
