"""The journal survives kill -9 at any moment: every committed row is there, nothing half-written."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from controller.journal.store import Journal, JournalError

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[2]

WRITER = r"""
import sys
from controller.journal.store import Journal
j = Journal(sys.argv[1])
j.start_job("abc123", "demo", "robot", "{}")
i = 0
while True:
    i += 1
    j.moves_sent([(i, 0, 0, i, "weld")])
    j.progress(i, 0, 0, i)
    if i % 10 == 0:
        j.samples([(float(i), 120.0, 20.0, 5.0, 100.0, 0, 0)] * 20)
    sys.stdout.write(f"{i}\n"); sys.stdout.flush()
"""


def test_kill_9_while_writing_loses_nothing_committed(tmp_path: Path) -> None:
    path = tmp_path / "journal.sqlite"
    committed_total = 0
    for k, delay in enumerate((0.15, 0.3, 0.05, 0.4, 0.2)):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], cwd=ROOT, stdout=subprocess.PIPE,
                                text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        # wait for the first committed row, then kill at a moment that varies from run to run
        first = proc.stdout.readline()
        assert first.strip(), "writer did not start"
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        out, _ = proc.communicate()
        reported = [int(x) for x in [first, *out.split()] if str(x).strip()]
        last_reported = max(reported)
        j = Journal(path)
        assert j.query("PRAGMA integrity_check") == [("ok",)]
        rows = j.query("SELECT ticket, idx FROM progress WHERE run=?", (k + 1,))
        tickets = [r[0] for r in rows]
        # every row the writer saw committed is there; at most the row in flight beyond it
        assert tickets == list(range(1, len(tickets) + 1))
        assert last_reported <= len(tickets) <= last_reported + 1
        # the write-ahead rule holds: no progress without its move row
        orphans = j.query("SELECT count(*) FROM progress p WHERE NOT EXISTS "
                          "(SELECT 1 FROM moves m WHERE m.ticket=p.ticket AND m.run=p.run)")
        assert orphans == [(0,)]
        committed_total += len(tickets)
        assert j.run == k + 2  # the next opening is a new run
        j.close()
    assert committed_total > 50


def test_pass_progress_replays_the_append_only_rows(tmp_path: Path) -> None:
    j = Journal(tmp_path / "j.sqlite")
    j.start_job("h1", "part", "robot", "{}")
    j.pass_state(0, 0, "started")
    j.pass_state(0, 0, "arc_on")
    for idx in (1, 2, 3):
        j.progress(100 + idx, 0, 0, idx)
    j.pass_state(0, 0, "done")
    j.pass_state(0, 1, "started")
    j.pass_state(0, 1, "arc_on")
    j.progress(200, 0, 1, 1)
    j.pass_state(0, 1, "interrupted", reason="door open")
    j.close()
    j2 = Journal(tmp_path / "j.sqlite")
    prog = j2.pass_progress()
    assert prog[(0, 0)].state == "done" and prog[(0, 0)].done_idx == 3
    assert prog[(0, 1)].state == "interrupted" and prog[(0, 1)].done_idx == 1
    assert (1, 0) not in prog
    with pytest.raises(JournalError, match="belongs to job h1"):
        j2.start_job("other", "part", "robot", "{}")
    assert j2.query("PRAGMA journal_mode") == [("wal",)]
    assert j2.query("PRAGMA synchronous") == [(2,)]  # FULL


def test_progress_a_robot_took_back_is_withdrawn_so_a_resume_redoes_those_moves(tmp_path: Path) -> None:
    # a lying robot's EXEs for tickets 106-110 (points 6-10), then its real EXE of 105: the
    # build withdraws the progress past point 5; a resume re-arcs there, not at point 10
    j = Journal(tmp_path / "j.sqlite")
    j.start_job("h1", "part", "robot", "{}")
    j.pass_state(0, 0, "started")
    j.pass_state(0, 0, "arc_on")
    for idx in range(1, 11):
        j.progress(100 + idx, 0, 0, idx)
    j.progress(300, 0, 1, 4)                        # another pass: untouched
    j.retract(0, 0, 5, "robot took back its EXEs after ticket 105")
    j.pass_state(0, 0, "interrupted", reason="protocol fault")
    j.close()
    j2 = Journal(tmp_path / "j.sqlite")
    prog = j2.pass_progress()
    assert prog[(0, 0)].done_idx == 5 and prog[(0, 1)].done_idx == 4
    assert j2.query("SELECT count(*) FROM progress WHERE pass=0") == [(10,)]   # append-only: nothing deleted
    alarms = [m for (m,) in j2.query("SELECT message FROM events WHERE kind='alarm'")]
    assert any("took back" in m for m in alarms), alarms
    j2.progress(401, 0, 0, 7)                       # the resumed bead's own progress counts again
    assert j2.pass_progress()[(0, 0)].done_idx == 7


def test_background_writer_commits_in_order_and_reads_see_every_write(tmp_path: Path) -> None:
    j = Journal(tmp_path / "j.sqlite", background=True)
    j.start_job("h", "part", "robot", "{}")
    j.pass_state(0, 0, "started")
    for i in range(500):
        j.progress(i + 1, 0, 0, i + 1)
    j.pass_state(0, 0, "done")
    # a read waits for the queued writes: the replay sees the last one
    prog = j.pass_progress()
    assert prog[(0, 0)].state == "done" and prog[(0, 0)].done_idx == 500
    assert [r[0] for r in j.query("SELECT ticket FROM progress ORDER BY id")] == list(range(1, 501))
    j.close()
    assert Journal(tmp_path / "j.sqlite").query("SELECT count(*) FROM progress") == [(500,)]
