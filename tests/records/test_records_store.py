"""The shop's record store (issue 39 items 2-5, docs/records.md), against a real PostgreSQL server
the session starts itself and against SQLite: versioned schema, idempotent sending, the queue that
survives an outage, `cell records sync` and `cell records query`."""
from __future__ import annotations

import csv
import datetime as dt
import json
from pathlib import Path

import pytest

from bench._records_data import fake_record
from controller.cli.main import main
from controller.records.db import connect
from controller.records.queue import PENDING, after_build, mark_pending
from controller.records.schema import LATEST
from controller.records.send import send_record
from tests.records.lot_config import cell_yaml


def _count(url: str, sql: str, params: tuple = ()) -> int:
    st = connect(url)
    try:
        return int(st.rows(sql, params)[0][0])
    finally:
        st.close()


def test_a_record_is_stored_once_however_often_it_is_sent_and_reads_back_equal(store_url: str) -> None:
    rec = fake_record(1, beads=12, defect_every=5)
    st = connect(store_url)
    try:
        assert send_record(st, rec, run_dir="/runs/a") == "stored"
        assert send_record(st, rec, run_dir="/runs/a") == "unchanged"
        assert st.rows("SELECT count(*) FROM builds")[0][0] == 1
        assert st.rows("SELECT count(*) FROM beads")[0][0] == 12
        (text,) = st.rows("SELECT record FROM builds WHERE build_id = ?", (rec["build_id"],))[0]
        assert json.loads(text) == rec
        # the same build, finished by a resume: its rows replaced whole, never a second build
        newer = {**rec, "state": "complete", "beads": rec["beads"] + [dict(rec["beads"][0], layer=9)]}
        assert send_record(st, newer) == "replaced"
        assert st.rows("SELECT count(*), max(state) FROM builds") == [(1, "complete")]
        assert st.rows("SELECT count(*) FROM beads")[0][0] == 13
        # versioned schema: applied once, connecting again changes nothing
        assert st.rows("SELECT version FROM schema_migrations") == [(LATEST,)]
    finally:
        st.close()
    assert _count(store_url, "SELECT count(*) FROM schema_migrations") == 1


def test_a_record_that_cannot_be_sent_is_queued_and_sync_sends_it_once(store_url: str, tmp_path: Path,
                                                                        capsys) -> None:
    runs = tmp_path / "runs"
    dirs = []
    for i in range(3):
        d = runs / f"job-{i}"
        d.mkdir(parents=True)
        (d / "report.json").write_text(json.dumps(fake_record(i, beads=4)))
        dirs.append(d)
    down = "postgresql://cell@127.0.0.1:9/none" if store_url.startswith("postgresql") else \
        f"sqlite:///{tmp_path / 'a-file' / 'shop.sqlite'}"
    (tmp_path / "a-file").write_text("not a directory")   # the store cannot be opened
    res = after_build(dirs[0], runs, down, cell="cell-07", timeout_s=1.0)
    assert res.queued == [str(dirs[0])] and res.errors and (dirs[0] / PENDING).is_file()
    assert "being sent" not in json.loads((dirs[0] / PENDING).read_text())["reason"]
    mark_pending(dirs[1], "build ended: being sent")   # a writer that died before sending
    # the next build's end sends its own record and every queued one of the runs directory
    res = after_build(dirs[2], runs, store_url, cell="cell-07")
    assert sorted(res.sent) == sorted(map(str, dirs)) and not res.queued
    assert not any((d / PENDING).exists() for d in dirs)
    assert _count(store_url, "SELECT count(*) FROM builds") == 3
    assert _count(store_url, "SELECT count(*) FROM cells") == 1   # the records' own cell (cell-01)
    # `cell records sync`: a record queued again (sent twice in effect) is still stored once
    mark_pending(dirs[0], "queued by hand")
    cfg = cell_yaml(tmp_path, url=store_url)
    assert main(["records", "sync", "--cell-config", str(cfg), "--runs", str(runs), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["sent"], out["unchanged"], out["queued"]) == (0, 1, 0)
    assert _count(store_url, "SELECT count(*) FROM builds") == 3
    # an unreachable store: exit 1, the record stays queued with the reason
    mark_pending(dirs[1], "queued by hand")
    assert main(["records", "sync", "--url", down, "--cell-config", str(cfg), "--runs", str(runs), "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["queued"] == 1 and out["errors"] and (dirs[1] / PENDING).is_file()


def test_query_finds_defective_beads_by_lot_material_cell_and_date_with_arc_time_and_heat(
        store_url: str, tmp_path: Path, capsys) -> None:
    st = connect(store_url)
    t0 = dt.datetime(2026, 11, 20, tzinfo=dt.timezone.utc)
    try:
        for i in range(12):
            rec = fake_record(i, beads=8, lot="LOT-X" if i % 3 == 0 else "LOT-Y", cell=f"cell-{i % 2}",
                              defect_every=4 if i % 2 == 0 else 0, started=t0 + dt.timedelta(days=i))
            send_record(st, rec)
    finally:
        st.close()
    cfg = cell_yaml(tmp_path, url=store_url)
    q = ["records", "query", "--cell-config", str(cfg), "--json"]
    assert main([*q, "--defects", "--wire-lot", "LOT-X"]) == 0
    out = json.loads(capsys.readouterr().out)
    # builds 0, 6 (LOT-X, even: 2 defective beads each); 3 and 9 are LOT-X without defects
    assert out["kind"] == "beads" and out["count"] == 4
    assert {r["wire_lot"] for r in out["rows"]} == {"LOT-X"} and all(r["defects_count"] > 0 for r in out["rows"])
    assert {(r["layer"], r["pass"]) for r in out["rows"]} == {(0, 3), (1, 3)}
    assert {"cell", "job_name", "material", "defect_reasons"} <= set(out["rows"][0])
    assert main([*q, "--defects", "--cell", "cell-1"]) == 0
    assert json.loads(capsys.readouterr().out)["count"] == 0
    assert main([*q, "--material", "er70s6-1.2mm", "--since", "2026-11-26", "--csv", str(tmp_path / "b.csv")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["started"][:10] for r in out["rows"]] == ["2026-12-01", "2026-11-29", "2026-11-27"]  # odd i, newest first
    r = out["rows"][0]
    assert r["arc_time_s"] > 0 and r["heat_input_kj"] > 0 and abs(r["heat_input_kj"] * 1000 / 320 - r["heat_input_j_mm"]) < 0.01
    rows = list(csv.DictReader((tmp_path / "b.csv").open()))
    assert len(rows) == 3 and rows[0]["build_id"] == r["build_id"]
    assert main([*q, "--since", "yesterday"]) == 2
    assert capsys.readouterr().err.startswith("error: --since 'yesterday'")


def test_records_commands_need_a_store(tmp_path: Path, capsys) -> None:
    cfg = cell_yaml(tmp_path)
    assert main(["records", "query", "--cell-config", str(cfg)]) == 2
    assert "no record store" in capsys.readouterr().err
    assert main(["records", "sync", "--url", "mysql://x", "--cell-config", str(cfg)]) == 2
    assert "expected sqlite:///PATH" in capsys.readouterr().err


@pytest.mark.realtime
def test_a_build_sends_its_record_at_its_end_equal_to_its_report(store_url: str, tmp_path: Path, capsys) -> None:
    from tests.cells import small_job

    jf = tmp_path / "job.json"
    jf.write_text(json.dumps(small_job(1)))
    cfg = cell_yaml(tmp_path, url=store_url, wire_lot="HX-1")
    assert main(["run", str(jf), "--sim", "--cell-config", str(cfg), "--runs", str(tmp_path / "runs"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    run_dir = Path(out["run_dir"])
    rep = json.loads((run_dir / "report.json").read_text())
    assert not (run_dir / PENDING).exists()
    st = connect(store_url)
    try:
        (text, lot, cell), = st.rows("SELECT record, wire_lot, cell FROM builds")
        assert json.loads(text) == rep and (lot, cell) == ("HX-1", "demo-cell")
        assert st.rows("SELECT count(*) FROM beads")[0][0] == len(rep["beads"]) == 2
    finally:
        st.close()


def test_the_database_stopped_and_started_again_loses_nothing(pg_server, tmp_path: Path) -> None:
    """An outage of the real server: the record ending meanwhile is queued, the next build's end
    (the server back) sends it and its own, each once."""
    url = pg_server.create_db("outage")
    runs = tmp_path / "runs"
    dirs = []
    for i in range(2):
        d = runs / f"job-{i}"
        d.mkdir(parents=True)
        (d / "report.json").write_text(json.dumps(fake_record(100 + i, beads=6)))
        dirs.append(d)
    assert after_build(dirs[0], runs, url, cell="c").sent == [str(dirs[0])]
    (dirs[0] / "report.json").write_text(json.dumps({**fake_record(100, beads=6), "state": "fault"}))
    pg_server.stop()
    try:
        res = after_build(dirs[0], runs, url, cell="c", timeout_s=1.0)
        assert res.queued == [str(dirs[0])] and "127.0.0.1" in res.errors[0]
    finally:
        pg_server.start()
    res = after_build(dirs[1], runs, url, cell="c")
    assert sorted(res.sent) == sorted(map(str, dirs)) and not any((d / PENDING).exists() for d in dirs)
    st = connect(url)
    try:
        assert st.rows("SELECT count(*), count(DISTINCT build_id) FROM builds") == [(2, 2)]
        assert st.rows("SELECT state FROM builds WHERE build_id = ?", (fake_record(100, beads=6)["build_id"],)) == [("fault",)]
        assert st.rows("SELECT count(*) FROM beads")[0][0] == 12
    finally:
        st.close()
