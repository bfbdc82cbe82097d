"""A large job's arrays are written straight from numpy (planner/job.py, orjson): the same bytes
as json writes the job's dictionary."""
from __future__ import annotations

import json

import numpy as np
import pytest

from planner import job as jobfile
from planner.job import BeadInfo, Interpass, Job, Layer, Pass, Source, job_to_dict, job_to_json


def _json(job: Job) -> bytes:
    return (json.dumps(job_to_dict(job), sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n").encode()


def _job(n: int, seed: int = 3) -> Job:
    """Passes whose numbers round to every kind of text: small, negative, whole, large, tiny normals."""
    rng = np.random.default_rng(seed)
    layers = []
    for i in range(4):
        pts = np.column_stack([rng.normal(0, 300, n), rng.uniform(-1e-3, 1e-3, n) * 10 ** rng.integers(0, 9, n),
                               np.full(n, 0.44 * (i + 1))])
        pts[::7, 0] = np.round(pts[::7, 0])   # whole numbers: "12.0"
        nrm = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-5, 1, size=(n, 1))
        seg = rng.uniform(0.05, 9000.0, n - 1)
        passes = (Pass("perimeter", 4.123456, 150.126, 800.04, 6.5004, pts, nrm, seg_speed_mm_min=seg),
                  Pass("infill", 4.0, 150.0, 812.0, 6.5, pts[: n // 2] * -1.0, None, None, False,
                       None, rng.uniform(4.0, 7.4, n // 2 - 1)))
        layers.append(Layer(i, 0.44 * (i + 1), 0.44, passes, Interpass(150.0, 60.0), {"coverage": 0.99123}))
    summary = {"warnings": ["feature at (1.0, 2.0) \u2265 3 mm \u2013 wide"], "tiny": 1.2e-05, "big": 1.5e17}
    return Job(Source("p\u00fcmp\u0001 \\u0001 2.stl", "ab" * 32, "mm"), {"name": "Inconel 718"},
               BeadInfo(4.0, 0.44, 2.95, "parabola/tangent"), tuple(layers), summary)


def test_a_large_job_is_written_as_json_writes_it():
    job = _job(6000)
    assert sum(len(p.points) for L in job.layers for p in L.passes) >= jobfile.BULK_POINTS
    out = job_to_json(job)
    assert out == _json(job)
    assert json.loads(out)["layers"][0]["passes"][0]["speed_mm_min"][0] > 0


def test_a_small_job_written_in_bulk_gives_the_same_bytes(monkeypatch):
    import orjson

    written: list[int] = []
    real = orjson.dumps

    def counted(obj: object, option: int | None = None) -> bytes:
        written.append(1)
        return real(obj, option=option)

    monkeypatch.setattr(orjson, "dumps", counted)
    monkeypatch.setattr(jobfile, "BULK_POINTS", 0)
    for seed in range(5):
        job = _job(50, seed)
        assert job_to_json(job) == _json(job)
    assert len(written) == 5 * 4 * 5   # every layer's arrays: points, normals, speeds; points, wire feeds


def test_a_point_that_is_no_number_is_refused_as_before(monkeypatch):
    monkeypatch.setattr(jobfile, "BULK_POINTS", 0)
    job = _job(50)
    job.layers[1].passes[0].points[3, 0] = np.nan
    with pytest.raises(ValueError):
        job_to_json(job)
