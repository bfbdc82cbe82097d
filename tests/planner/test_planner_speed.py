"""Plan-time work that does not scale with the part is not done at plan time (issue 28 item 7)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from planner.bead import SOLVED_RATIOS, _critical_ratio


@pytest.mark.parametrize("profile", sorted(SOLVED_RATIOS))
def test_the_kept_critical_ratios_are_the_solved_ones(profile):
    assert SOLVED_RATIOS[profile] == pytest.approx(_critical_ratio(profile, 0.25, solve=True), abs=1e-12)
    assert SOLVED_RATIOS["parabola"] == pytest.approx(0.738, abs=5e-4)  # Ding 2015: d* = 0.738 w


def test_planning_imports_no_scipy_trimesh_or_matplotlib():
    """A binary-STL plan loads none of the heavy optional libraries (start-up time)."""
    code = ("import sys; import planner.plan, planner.mesh, controller.cli.plan; "
            "print(sorted(m for m in ('scipy', 'trimesh', 'matplotlib', 'networkx') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


_PLAN_MODULES = ("import json, sys\n"
                 "from controller.cli.main import main\n"
                 "rc = main(sys.argv[1:])\n"
                 "heavy = ('pydantic', 'yaml', 'trimesh', 'scipy', 'matplotlib', 'numpy.ma', 'core.config', 'tqdm',\n"
                 "         'textual', 'asyncua', 'pymodbus', 'serial', 'psycopg', 'sqlite3', 'drivers', 'sims',\n"
                 "         'controller.runtime', 'controller.tui', 'controller.report', 'controller.opcua',\n"
                 "         'controller.journal', 'controller.motion')\n"
                 "sys.stderr.write(json.dumps({'rc': rc, 'loaded': sorted(m for m in heavy if m in sys.modules)}))\n")


def _plan(tmp_path, cache, *extra):
    """`cell plan` of a binary STL in a fresh interpreter: (exit status, heavy modules it loaded, job bytes)."""
    # trimesh only to write the test's mesh; the plan runs in its own interpreter
    import trimesh

    stl = tmp_path / "block.stl"
    if not stl.exists():
        stl.write_bytes(trimesh.creation.box(extents=(40.0, 20.0, 6.0)).export(file_type="stl"))
    out = tmp_path / "block.job.json"
    env = {**os.environ, "CELL_CACHE_DIR": str(cache)}
    proc = subprocess.run([sys.executable, "-c", _PLAN_MODULES, "plan", str(stl), "--width", "6", "--out", str(out),
                           "--json", *extra], capture_output=True, text=True, env=env, cwd=tmp_path)
    report = json.loads(proc.stderr.strip().splitlines()[-1])
    return report["rc"], report["loaded"], out.read_bytes() if report["rc"] == 0 else b""


def test_a_remembered_configuration_plans_without_pydantic_yaml_or_trimesh(tmp_path):
    """The second `cell plan` reads the validated cell and material from the cache: no pydantic,
    no PyYAML, no trimesh, no numpy.ma on its path, none of the controller's runtime (devices, TUI,
    OPC UA, Modbus, serial, record stores: issue 40 item 3), and the same job byte for byte."""
    cache = tmp_path / "cache"
    rc, first_loaded, first = _plan(tmp_path, cache)
    assert rc == 0 and "pydantic" in first_loaded  # the first one validates config/ and remembers it
    rc, loaded, again = _plan(tmp_path, cache)
    assert rc == 0 and loaded == []
    assert again == first
    assert sorted(p.name.split("-")[0] for p in cache.glob("*.json")) == ["cell", "material"]


def test_an_edited_material_file_is_validated_again(tmp_path):
    """The cache is keyed by the file's bytes: an edit is seen at once, a broken file is an error every time."""
    cache = tmp_path / "cache"
    src = Path(__file__).resolve().parents[2] / "config" / "materials" / "inconel718-1.0mm.yaml"
    mat = tmp_path / "mine.yaml"
    mat.write_text(src.read_text())
    rc, _, before = _plan(tmp_path, cache, "--material", str(mat))
    assert rc == 0
    text = src.read_text()
    assert "dwell_s:" in text
    mat.write_text(re.sub(r"dwell_s: *[0-9.]+", "dwell_s: 7.5", text))
    rc, loaded, after = _plan(tmp_path, cache, "--material", str(mat))
    assert rc == 0 and "pydantic" in loaded and after != before
    assert json.loads(after)["layers"][0]["interpass"]["dwell_s"] == 7.5
    rc, _, fresh = _plan(tmp_path, tmp_path / "other-cache", "--material", str(mat))
    assert fresh == after  # remembered or validated, the same job
    mat.write_text(text.replace("dwell_s:", "dwell_seconds:"))
    for _ in range(2):
        rc, loaded, _ = _plan(tmp_path, cache, "--material", str(mat))
        assert rc == 2 and "pydantic" in loaded


def test_layers_planned_side_by_side_give_the_job_planned_one_by_one(monkeypatch):
    """The layers the memo does not have are planned on worker threads (planner.ahead): the job is
    the same byte for byte on one thread or three."""
    import trimesh  # the test's part

    from core.config import load_material
    from planner import ahead
    from planner.job import job_to_json
    from planner.plan import PlanOptions, plan_part

    mesh = trimesh.creation.torus(major_radius=30.0, minor_radius=8.0, major_sections=48, minor_sections=24)
    opts = PlanOptions(width_mm=6.0, allow_overhang=True, allow_underfill=True)
    mat = load_material("inconel718-1.0mm")
    jobs = []
    for n in (1, 3):
        monkeypatch.setattr(ahead, "workers", lambda n=n: n)
        jobs.append(job_to_json(plan_part(mesh, opts, mat)))
    assert len(jobs[0]) > 10_000 and jobs[0] == jobs[1]


_LEVELLED_ON_PROCESSES = """
import json, multiprocessing
import trimesh
from core.config import load_material
from planner import plan as pp, processes
from planner.ahead import workers

processes.spare_cores = lambda n: True   # the pool whatever the host's load (a loaded host plans in one process)
from planner.job import job_to_json
from planner.plan import PlanOptions, plan_part

seen = []
mesh = trimesh.creation.cylinder(radius=9.0, height=28.0, sections=40)
opts = PlanOptions(width_mm=6.0, allow_underfill=True, allow_overhang=True)
mat = load_material("inconel718-1.0mm")
pooled = job_to_json(plan_part(mesh, opts, mat, progress=lambda i, n: seen.append(len(multiprocessing.active_children()))))
pp.MIN_LAYERS = 10 ** 9
alone = job_to_json(plan_part(mesh, opts, mat))
print(json.dumps({"same": pooled == alone, "size": len(alone), "children": max(seen), "cores": workers(),
                  "left": len(multiprocessing.active_children())}))
"""


def test_layers_levelled_on_worker_processes_give_the_job_levelled_in_turn():
    """A `cell plan` of 40 layers or more levels its layers on forked worker processes
    (planner.processes, one a core): the job is the same byte for byte as levelled in turn, and no
    worker is left once the plan returns. In a fresh interpreter: the pool forks only a process
    that has no other thread (and, outside this test, only on a host with a core to spare)."""
    out = subprocess.run([sys.executable, "-c", _LEVELLED_ON_PROCESSES], capture_output=True, text=True, check=True)
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["size"] > 10_000 and report["same"]
    assert report["children"] == (report["cores"] if report["cores"] > 1 else 0)
    assert report["left"] == 0
