"""The job checked against the cell before any device is touched (issue 14, docs/contract.md §6)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from controller.cli.main import main
from controller.job.check import JobCheckError, check_job, violations
from controller.job.model import CellJob
from controller.job.read import job_from_dict, read_job
from core.errors import InputError
from core.config import load_cell, load_material
from tests.cells import small_job

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

CFG = load_cell()
MAT = load_material("inconel718-1.0mm")


def _edit(**kw) -> dict:
    job = small_job(2)
    layer = kw.pop("layer", 1)
    p = job["layers"][layer]["passes"][0]
    for k, v in kw.items():
        if k == "point":
            p["points"][2] = v
        elif k == "interpass":
            job["layers"][layer]["interpass"] = v
        else:
            p[k] = v
    return job


def _with_speed(job: CellJob, layer: int, pass_: int, speed: float) -> CellJob:
    """The typed job with one pass's speed set past what a job file may say (a reader would refuse it)."""
    la = job.layers[layer]
    passes = tuple(dataclasses.replace(p, speed_mm_min=speed) if k == pass_ else p for k, p in enumerate(la.passes))
    layers = tuple(dataclasses.replace(la, passes=passes) if k == layer else x for k, x in enumerate(job.layers))
    return dataclasses.replace(job, job=dataclasses.replace(job.job, layers=layers))


def test_the_planned_job_fits_the_cell() -> None:
    assert violations(job_from_dict(small_job(3)), CFG, MAT) == []


@pytest.mark.parametrize("edit, needle", [
    ({"point": [600.0, 0.0, 1.0]}, "point 2: (600, 0, 1) mm lies outside the workspace"),
    ({"point": [1e9, 0.0, 1.0]}, "outside the workspace"),
    ({"speed_mm_min": 7000}, "speed_mm_min 7000 is outside (0, 6000]"),
    ({"speed_mm_min": 1e9}, "speed_mm_min 1e+09"),
    ({"speed_mm_min": 1e-9}, "below the slowest weld 30 mm/min"),
    ({"current_a": 1000}, "current_a 1000 A is outside"),
    ({"current_a": 1e9}, "current_a 1e+09 A"),
    ({"wfs_m_min": 100}, "wfs_m_min 100 m/min is outside"),
    ({"interpass": {"max_temperature_c": -1, "dwell_s": 0}}, "interpass max_temperature_c -1 °C is outside (20, 400]"),
])
def test_each_violation_is_named(edit: dict, needle: str | None) -> None:
    found = violations(job_from_dict(_edit(**edit)), CFG, MAT)
    if needle is None:
        return
    assert found and found[0].layer == 1 and needle in f"{found[0].where()}: {found[0].what}"


def test_a_standing_torch_is_refused(tmp_path: Path) -> None:
    # a job file that says so is refused when it is read, naming the file and the field
    jp = tmp_path / "j.json"
    jp.write_text(json.dumps(_edit(speed_mm_min=0.0)))
    with pytest.raises(InputError, match=r"j\.json: layers\[1\]\.passes\[0\]\.speed_mm_min must be > 0, got 0\.0"):
        read_job(jp)
    # and the check against the cell refuses it too (a typed job built in memory)
    with pytest.raises(JobCheckError, match=r"layer 1, pass 0: speed_mm_min 0 is outside \(0, 6000\]"):
        check_job(_with_speed(job_from_dict(small_job(2)), 1, 0, 0.0), CFG, MAT, "j.json")


def test_the_alignment_transform_moves_points_out_of_the_workspace() -> None:
    job = small_job(2)
    job["alignment"] = {"transform": [[1, 0, 0, 495], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
    found = violations(job_from_dict(job), CFG, MAT)
    assert found and "outside the workspace" in found[0].what


def test_the_error_names_the_first_violation_and_counts_them() -> None:
    job = small_job(3)
    for la in job["layers"]:
        for p in la["passes"]:
            p["current_a"] = 1000
    with pytest.raises(JobCheckError) as ei:
        check_job(job_from_dict(job), CFG, MAT, "hand-edited.json")
    msg = str(ei.value)
    assert msg.startswith("hand-edited.json: job refused before any motion: layer 0, pass 0: current_a 1000 A")
    assert "(6 violations in all" in msg


def test_outside_envelope_passes_run_only_where_the_cell_allows_them() -> None:
    job = job_from_dict(_edit(current_a=200, inside_envelope=False))
    assert violations(job, CFG, MAT)  # cell.yaml does not allow it
    allowed = CFG.model_copy(update={"limits": CFG.limits.model_copy(update={"allow_outside_envelope": True})})
    assert violations(job, allowed, MAT) == []
    job = job_from_dict(_edit(current_a=1e9, inside_envelope=False))
    assert "power source's range" in violations(job, allowed, MAT)[0].what


def _run(tmp: Path, job: dict, capsys, *extra: str) -> tuple[int, str, Path]:
    jp = tmp / "job.json"
    jp.write_text(json.dumps(job))
    log = tmp / "simlog"
    rc = main(["run", str(jp), "--sim", "--runs", str(tmp / "runs"), "--sim-log", str(log), *extra])
    return rc, capsys.readouterr().err, log


@pytest.mark.parametrize("edit", [{"point": [600.0, 0.0, 1.0]}, {"speed_mm_min": 1e9}, {"current_a": 1000},
                                  {"speed_mm_min": 1e-9}, {"wfs_m_min": 100},
                                  {"interpass": {"max_temperature_c": -1, "dwell_s": 0}}])
def test_cell_run_refuses_before_any_device_and_the_simulators_log_nothing(tmp_path: Path, capsys, edit) -> None:
    rc, err, log = _run(tmp_path, _edit(**edit), capsys)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "job refused before any motion" in lines[0]
    assert "Traceback" not in err
    # no simulator ran: no deposit and no execution log (nor a run directory with a journal)
    logs = list(log.glob("*.jsonl")) if log.exists() else []
    assert all(p.stat().st_size == 0 for p in logs)
    assert not list((tmp_path / "runs").glob("*/journal.sqlite"))


def test_too_many_points_are_refused(tmp_path: Path) -> None:
    from controller.job import read

    job = small_job(1)
    job["layers"][0]["passes"][0]["points"] = [[1.0, 1.0, 1.0]] * (read.MAX_POINTS_PER_PASS + 1)
    with pytest.raises(InputError, match=r"big\.json: layers\[0\]\.passes\[0\] has 1000001 points, over the limit"):
        job_from_dict(job, "big.json")


def test_max_step_has_a_floor(tmp_path: Path, capsys) -> None:
    jp = tmp_path / "job.json"
    jp.write_text(json.dumps(small_job(1)))
    for bad in ("0", "nan", "-1", "inf", "1e-9"):
        assert main(["run", str(jp), "--max-step", bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and "--max-step" in err and "Traceback" not in err
