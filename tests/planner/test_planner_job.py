"""Job file `cell-job/1`: the schema of docs/contract.md §3, same input same bytes, a validating reader."""
from __future__ import annotations

import json

import numpy as np
import pytest

from core.config import load_material
from core.errors import InputError
from planner.job import job_to_dict, job_to_json, load_job, loads_job
from planner.plan import PlanOptions, plan_part

from tests import planner_parts as parts

MAT = load_material("inconel718-1.0mm")


@pytest.fixture(scope="module")
def job_bytes():
    return job_to_json(plan_part(parts.plate_with_holes(), PlanOptions(width_mm=6.0), MAT))


def test_same_input_gives_the_same_bytes(job_bytes):
    again = job_to_json(plan_part(parts.plate_with_holes(), PlanOptions(width_mm=6.0), MAT))
    assert again == job_bytes


def test_schema_fields_as_in_the_design(job_bytes):
    d = json.loads(job_bytes)
    arrays = any(isinstance(p["speed_mm_min"], list) or isinstance(p["wfs_m_min"], list)
                 for L in d["layers"] for p in L["passes"])
    assert d["schema"] == ("cell-job/2" if arrays else "cell-job/1")   # per-segment speeds: cell-job/2
    assert set(d["source"]) == {"file", "sha256", "units"}
    assert d["material"]["name"] == MAT.name
    assert set(d["bead"]) == {"width_mm", "height_mm", "step_over_mm", "model"}
    assert d["bead"]["step_over_mm"] == pytest.approx(0.738 * 6.0, rel=0.01)  # Ding 2015 d*
    assert d["bead"]["height_mm"] == pytest.approx(0.11 * 6.0)  # RATIO · w
    layer = d["layers"][0]
    assert {"index", "z_mm", "height_mm", "passes", "interpass"} <= set(layer)
    assert layer["interpass"] == {"max_temperature_c": 150.0, "dwell_s": 60.0}
    zs = [L["z_mm"] for L in d["layers"]]
    assert np.allclose(np.diff(zs), d["bead"]["height_mm"])
    for p in layer["passes"]:
        assert p["role"] in ("perimeter", "infill", "gap")
        assert {"width_mm", "current_a", "speed_mm_min", "wfs_m_min", "points"} <= set(p)
        assert all(len(pt) == 3 for pt in p["points"])
        for key in ("speed_mm_min", "wfs_m_min"):   # one number, or one per segment
            assert not isinstance(p[key], list) or len(p[key]) == len(p["points"]) - 1
        if "normals" in p:
            n = np.array(p["normals"])
            assert n.shape == (len(p["points"]), 3) and np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-3)
    for key in ("layers", "passes", "arc_starts", "deposit_length_mm", "volume_mm3", "coverage", "est_time_s"):
        assert key in d["summary"]


def test_reader_round_trips(job_bytes):
    job = loads_job(job_bytes)
    assert job_to_json(job) == job_bytes
    assert job.layers[3].passes[0].points.shape[1] == 3


@pytest.mark.parametrize("path, value, field", [
    (("schema",), "cell-job/9", "schema"),
    (("layers", 1, "passes", 0, "role"), "weave", "layers[1].passes[0].role"),
    (("layers", 0, "passes", 2, "current_a"), "high", "layers[0].passes[2].current_a"),
    (("layers", 2, "passes", 1, "points"), [[1, 2]], "layers[2].passes[1].points"),
    (("bead", "width_mm"), -6, "bead.width_mm"),
])
def test_bad_field_is_named(job_bytes, path, value, field):
    d = json.loads(job_bytes)
    node = d
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    with pytest.raises(InputError, match=field.replace("[", r"\[").replace("]", r"\]")):
        load_job(d)


def test_missing_field_and_bad_json_are_named(job_bytes):
    d = json.loads(job_bytes)
    del d["layers"][0]["passes"][0]["wfs_m_min"]
    with pytest.raises(InputError, match=r"missing field layers\[0\]\.passes\[0\]\.wfs_m_min"):
        load_job(d)
    with pytest.raises(InputError, match="not valid JSON"):
        loads_job(b"{not json")


def test_job_dict_has_no_negative_zero(job_bytes):
    assert b"-0.0," not in job_bytes and b"-0.0]" not in job_bytes
    assert job_to_dict(loads_job(job_bytes))["schema"] == json.loads(job_bytes)["schema"]


def test_same_bytes_across_processes_and_hash_seeds(tmp_path):
    import os
    import subprocess
    import sys

    from planner.extrude import stack

    stl = tmp_path / "mix.stl"
    wall = parts.thin_wall()
    wall.apply_translation([-40.0, -70.0, 0.0])  # beside the islands, not through them
    stl.write_bytes(stack(parts.islands(), wall).export(file_type="stl"))
    outs = []
    for seed in ("1", "2"):
        out = tmp_path / f"job{seed}.json"
        env = dict(os.environ, PYTHONHASHSEED=seed)
        proc = subprocess.run([sys.executable, "-m", "controller.cli.main", "plan", str(stl), "--width", "6",
                               "--out", str(out), "--json"], env=env, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


def test_progress_reports_every_layer():
    seen = []
    job = plan_part(parts.overhang(), PlanOptions(width_mm=6.0, allow_overhang=True), MAT, progress=lambda d, n: seen.append((d, n)))
    n = len(job.layers)
    assert seen == [(i, n) for i in range(1, n + 1)]
