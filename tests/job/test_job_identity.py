"""One typed job from the file to the build (issue 25): its identity stays what the journal was keyed on.

The job is read once (controller/job/read.py) and carried typed; the hash the journal and the run
directory are keyed on is computed when the file is read, from the file's own object, exactly as
the controller computed it before the job was typed (sha256 of the canonical JSON of the parsed
file). `tests/data/journal_old_partial.sqlite` is a journal written by that earlier controller
(commit c19b663: `cell run tests/data/job_hand.json --sim --fault wire_stick@layer=1`, stopped by
the fault after 2 of 4 passes): the new controller reports it and finishes its build.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from controller.cli.main import main
from controller.job.identity import job_hash, run_dir_for
from controller.job.read import job_from_dict, read_job
from core.config import load_material
from core.errors import InputError
from planner.job import job_to_dict, job_to_json
from planner.plan import PlanOptions, plan_part

from tests import planner_parts as parts

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

DATA = Path(__file__).parents[1] / "data"
HAND = DATA / "job_hand.json"        # hand-written: ints, odd rounding, -0.0, extra keys, a non-ASCII name
PLANNED = DATA / "job_planned.json"  # written by `cell plan` (planner.job.job_to_json)
# the hashes the controller of commit c19b663 keyed these files' journals and run directories on
PINNED = {HAND: ("5184b6c6556fb4cf91a2af0a8ab2bbbce3c42c11569f99fb23a8f2e5b80e8bfd", "Bracket-ü-rev-2-5184b6c6"),
          PLANNED: ("32a3c2d96fcbc4df1186bfca5479afb3bdbc5f67ee0fc36e78e87deb10c7d4cf", "mesh-32a3c2d9")}


def _old_hash(text: str) -> str:
    """The journal's job hash as the controller computed it on the parsed file, written out here."""
    return hashlib.sha256(json.dumps(json.loads(text), sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@pytest.mark.parametrize("path", [HAND, PLANNED], ids=["hand-written", "planned"])
def test_a_job_files_hash_and_run_directory_are_the_ones_earlier_journals_were_keyed_on(path: Path) -> None:
    job = read_job(path)
    assert job.hash == PINNED[path][0] == _old_hash(path.read_text(encoding="utf-8"))
    assert run_dir_for(job, "runs").name == PINNED[path][1]
    assert json.loads(job.json) == json.loads(path.read_text(encoding="utf-8"))   # what the journal stores


def test_the_hash_is_of_the_file_not_of_the_typed_job() -> None:
    """Recomputed from the typed job (the planner's writer rounds, drops unknown keys) it would differ
    for a hand-written file: so it is computed at read time and carried."""
    job = read_job(HAND)
    assert job_hash(job_to_dict(job.job)) != job.hash
    # the same object however it is laid out on disk: key order, indentation
    relaid = json.dumps(json.loads(HAND.read_text(encoding="utf-8")), indent=3, sort_keys=False)
    assert job_from_dict(json.loads(relaid)).hash == job.hash
    # another number is another job; so is an int where the file had a float, as it always was
    for key, value in (("wfs_m_min", 5.5000001), ("current_a", 120.0)):
        d = json.loads(HAND.read_text(encoding="utf-8"))
        d["layers"][0]["passes"][0][key] = value
        assert job_from_dict(d).hash != job.hash, key


def test_a_job_the_planner_writes_now_hashes_as_its_file_did() -> None:
    text = job_to_json(plan_part(parts.plate_with_holes(), PlanOptions(width_mm=6.0),
                                 load_material("inconel718-1.0mm"))).decode()
    job = job_from_dict(json.loads(text))
    assert job.hash == _old_hash(text)
    assert job_hash(job_to_dict(job.job)) == job.hash   # the planner's own bytes: typed and raw agree


def _old_run(tmp: Path) -> Path:
    run_dir = tmp / "runs" / PINNED[HAND][1]
    run_dir.mkdir(parents=True)
    shutil.copyfile(DATA / "journal_old_partial.sqlite", run_dir / "journal.sqlite")
    return run_dir


def test_a_journal_written_before_the_job_was_typed_is_reported(tmp_path: Path, capsys) -> None:
    run_dir = _old_run(tmp_path)
    assert main(["report", str(run_dir), "--no-plots", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["job"]["hash"] == PINNED[HAND][0] and out["job"]["name"] == "Bracket-ü-rev-2"
    assert (out["passes_done"], out["passes_total"], out["layers_done"], out["layers_total"]) == (2, 4, 1, 2)
    rep = json.loads((run_dir / "report.json").read_text())
    assert [b["status"] for b in rep["beads"]] == ["done", "done", "interrupted", "not built"]
    assert rep["beads"][3]["current_planned_a"] == 120 and rep["beads"][3]["length_planned_mm"] == pytest.approx(30.0)
    assert main(["runs", "--runs", str(tmp_path / "runs"), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["runs"]
    assert [(r["job"], r["layers_done"], r["layers_total"]) for r in rows] == [("Bracket-ü-rev-2", 1, 2)]


def test_a_journal_written_before_the_job_was_typed_is_finished_by_cell_run(tmp_path: Path, capsys) -> None:
    run_dir = _old_run(tmp_path)
    rc = main(["run", str(HAND), "--sim", "--runs", str(tmp_path / "runs"), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["state"] == "complete", out
    assert out["run_dir"] == str(run_dir)             # the same run directory: the job is the journal's
    assert out["passes_done"] == 4 and out["arc_starts"] == 2   # the two passes left, nothing built twice
    rep = json.loads(Path(out["report"]).read_text())
    assert rep["runs"] == 2 and rep["job"]["hash"] == PINNED[HAND][0]


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d["layers"][1]["passes"][0].pop("wfs_m_min"), "missing field layers[1].passes[0].wfs_m_min"),
    (lambda d: d["layers"][0]["passes"][1].update(points=[[0, 0, "x"], [1, 1, 1]]),
     "layers[0].passes[1].points must be a list of [x, y, z] numbers"),
    (lambda d: d.update(schema="cell-job/9"), "schema is 'cell-job/9', which this controller does not know"),
    (lambda d: d.update(alignment={"transform": [[1, 0, 0], [0, 1, 0]]}), "alignment.transform must be a 4x4 matrix"),
    (lambda d: d.update(repair={"cad": "c.stl", "bounds_mm": [1, 2, 3]}), "repair.bounds_mm must be [[x, y, z], [x, y, z]]"),
], ids=["missing", "points", "schema", "alignment", "repair"])
@pytest.mark.parametrize("command", ["run", "export", "align"])
def test_a_bad_job_file_is_one_error_line_naming_the_file_and_the_field(tmp_path: Path, capsys, edit, needle,
                                                                        command: str) -> None:
    d = json.loads(HAND.read_text(encoding="utf-8"))
    edit(d)
    jp = tmp_path / "bad.json"
    jp.write_text(json.dumps(d))
    argv = {"run": ["run", str(jp), "--sim", "--runs", str(tmp_path / "runs")],
            "export": ["export", str(jp), "--format", "gcode", "--out", str(tmp_path / "x.nc")],
            "align": ["align", "run", "--sim", "--job", str(jp)]}[command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"error: {jp}: ") and needle in err, err
    assert not (tmp_path / "runs").exists() and not (tmp_path / "x.nc").exists()


def test_a_job_built_in_memory_names_its_source() -> None:
    d = json.loads(HAND.read_text(encoding="utf-8"))
    d["layers"][0]["passes"][0]["speed_mm_min"] = -1
    with pytest.raises(InputError, match=r"^demo job: layers\[0\]\.passes\[0\]\.speed_mm_min must be > 0"):
        job_from_dict(d, "demo job")
