"""Journals are never lost (issue 14): a damaged journal is refused untouched, its WAL kept;
`cell journal check` says what is readable; a tampered job is refused; complete jobs and --new."""
from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import pytest

from controller.job.identity import canonical_json, job_hash, run_dir_for
from controller.job.read import job_from_dict
from controller.cli.main import main
from controller.journal.store import Journal
from tests.cells import small_job

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


def _journal(run_dir: Path, job: dict, done: int, rows: int = 3000) -> Path:
    """A journal of `job` with `done` passes done and enough samples to span many pages; the
    files are copied while the writer still holds them, so a -wal is there too."""
    src = run_dir.parent / "src"
    j = Journal(src / "journal.sqlite")
    j.start_job(job_hash(job), "square", "robot", canonical_json(job))
    k = 0
    for li, la in enumerate(job["layers"]):
        for pi, _ in enumerate(la["passes"]):
            if k < done:
                j.pass_state(li, pi, "started")
                j.pass_state(li, pi, "done")
            k += 1
    j.samples([(float(i), 120.0, 20.0, 5.5, 100.0, 0, 0) for i in range(rows)])
    j.query("PRAGMA wal_checkpoint(TRUNCATE)")  # most rows in the database file itself...
    j.event("info", "after the checkpoint")     # ...and the latest in the WAL
    run_dir.mkdir(parents=True)
    for f in src.iterdir():
        shutil.copy(f, run_dir / f.name)
    j.close()
    return run_dir / "journal.sqlite"


def _digest(run_dir: Path) -> dict[str, str]:
    # the -shm is SQLite's shared-memory index (rebuilt from the WAL), not part of the journal
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(run_dir.iterdir())
            if p.is_file() and not p.name.endswith("-shm")}


def _half(p: Path) -> None:
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


def _garbage(p: Path) -> None:
    data = bytearray(p.read_bytes())
    data[1024:3072] = b"\xde\xad\xbe\xef" * 512
    p.write_bytes(bytes(data))


def _empty(p: Path) -> None:
    p.write_bytes(b"")


@pytest.mark.parametrize("damage", [_half, _garbage, _empty])
def test_resume_refuses_a_damaged_journal_and_leaves_it_byte_for_byte(tmp_path: Path, capsys, damage) -> None:
    job = small_job(3)
    run_dir = tmp_path / "runs" / "square-0000"
    jp = _journal(run_dir, job, done=3)
    assert (run_dir / "journal.sqlite-wal").stat().st_size > 0
    damage(jp)
    before = _digest(run_dir)
    rc = main(["resume", str(run_dir), "--sim", "--runs", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith(f"error: journal {jp} is damaged (") and err.count("\n") == 1
    assert _digest(run_dir) == before  # main file, WAL and all: untouched, nothing added
    # `cell journal check` says so and what is readable, still without writing
    rc = main(["journal", "check", str(run_dir), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 1 and out["state"] == "damaged" and out["wal_bytes"] > 0
    assert _digest(run_dir) == before


def test_journal_check_of_a_healthy_journal_says_what_is_done(tmp_path: Path, capsys) -> None:
    job = small_job(3)
    run_dir = tmp_path / "runs" / "square-0000"
    _journal(run_dir, job, done=4)
    assert main(["journal", "check", str(run_dir), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["state"] == "healthy" and out["job_checksum_ok"] is True
    assert out["passes_done"] == 4 and out["last_done"] == {"layer": 1, "pass": 1}
    assert out["readable"]["samples"] == 3000
    assert main(["journal", "check", str(tmp_path / "nowhere")]) == 2


def test_a_tampered_job_in_the_journal_is_refused(tmp_path: Path, capsys) -> None:
    job = small_job(3)
    run_dir = tmp_path / "runs" / "square-0000"
    jp = _journal(run_dir, job, done=2)
    bad = json.loads(canonical_json(job))
    bad["layers"][2]["passes"][0]["current_a"] = 150
    db = sqlite3.connect(jp)
    db.execute("UPDATE job SET job_json=?", (canonical_json(bad),))
    db.commit()
    db.close()
    rc = main(["resume", str(run_dir), "--sim", "--runs", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert rc == 2 and "does not match its checksum" in err and "tampered" in err
    assert main(["journal", "check", str(run_dir), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["job_checksum_ok"] is False


def test_a_journal_never_opens_a_missing_database_beside_its_wal(tmp_path: Path) -> None:
    job = small_job(1)
    run_dir = tmp_path / "r"
    jp = _journal(run_dir, job, done=1)
    jp.unlink()
    before = _digest(run_dir)
    with pytest.raises(Exception, match="is damaged"):
        Journal(jp)
    assert _digest(run_dir) == before and not jp.exists()


def test_run_of_a_complete_job_says_so_and_new_builds_it_again(tmp_path: Path, capsys) -> None:
    job = small_job(1)
    runs = tmp_path / "runs"
    jf = tmp_path / "square.json"
    jf.write_text(json.dumps(job))
    run_dir = run_dir_for(job_from_dict(job), runs)
    _journal(run_dir, job, done=2, rows=10)
    before = _digest(run_dir)
    assert main(["run", str(jf), "--sim", "--runs", str(runs), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["already_complete"] is True and out["arc_starts"] == 0 and "already complete" in out["message"]
    assert _digest(run_dir) == before
    log = tmp_path / "simlog"
    assert main(["run", str(jf), "--sim", "--new", "--runs", str(runs), "--sim-log", str(log), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["state"] == "complete" and out["arc_starts"] >= 2
    assert out["run_dir"] == str(run_dir) + "-2"
    assert (log / "deposit.jsonl").stat().st_size > 0
    assert _digest(run_dir) == before  # the first build's journal is untouched


@pytest.mark.parametrize("flag", ["--runs", "--sim-log"])
def test_runs_and_sim_log_must_be_directories(tmp_path: Path, capsys, flag: str) -> None:
    jf = tmp_path / "job.json"
    jf.write_text(json.dumps(small_job(1)))
    f = tmp_path / "afile"
    f.write_text("x")
    args = ["run", str(jf), "--sim", flag, str(f)] + (["--runs", str(tmp_path / "runs")] if flag != "--runs" else [])
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "is a file, not a directory" in err
    assert main(["resume", "--runs", str(tmp_path / "missing")]) == 2
    assert capsys.readouterr().err.startswith("error: --runs")


def test_recovery_resumes_from_the_last_pass_the_journal_proves_done(tmp_path: Path, capsys) -> None:
    job = small_job(3)
    run_dir = tmp_path / "runs" / "square-0000"
    jp = _journal(run_dir, job, done=3, rows=20000)
    _half(jp)
    before = _digest(run_dir)
    assert main(["resume", str(run_dir), "--sim"]) == 2
    capsys.readouterr()
    assert main(["journal", "recover", str(run_dir), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["passes_done"] == 3 and rec["rows"]["job"] == 1
    assert _digest(run_dir) == before  # the damaged journal is evidence: never touched
    log = tmp_path / "simlog"
    rc = main(["resume", rec["run_dir"], "--sim", "--sim-log", str(log), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["state"] == "complete" and out["passes_done"] == 6
    db = sqlite3.connect(Path(rec["run_dir"]) / "journal.sqlite")
    rebuilt = set(db.execute("SELECT DISTINCT layer, pass FROM passes WHERE state='started' AND run > 1"))
    db.close()
    # only the three passes not proven done were deposited again; layer 0 was not rebuilt
    assert rebuilt == {(1, 1), (2, 0), (2, 1)}
    starts = [json.loads(ln)["from"] for ln in (log / "deposit.jsonl").read_text().splitlines()]
    assert starts and min(s[2] for s in starts) >= 1.99  # nothing deposited at z = 1 (layer 0)


def test_recovery_refuses_when_nothing_proves_where_the_build_stopped(tmp_path: Path, capsys) -> None:
    job = small_job(2)
    run_dir = tmp_path / "runs" / "square-0000"
    jp = _journal(run_dir, job, done=2)
    _empty(jp)
    jf = tmp_path / "job.json"
    jf.write_text(json.dumps(job))
    rc = main(["journal", "recover", str(run_dir), "--job", str(jf)])
    err = capsys.readouterr().err
    assert rc == 2 and "nothing proves where the build stopped" in err
    assert not (tmp_path / "runs" / "square-0000-recovered").exists()
