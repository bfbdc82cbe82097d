"""A late device cycle caused by the controller fails the test that built (docs/testing.md, "A loop that
never blocks").

Every build's journal holds the links' statistics at its end (an `events` row of kind `links`, the
same rows the record's `links` carries). After each test, every journal under the worker's
temporary directory that holds rows not yet seen is read (read-only: never a new run), and each
cyclic device (power source, cell I/O) must have `max_own_period_ms` at most `OWN_PERIOD_LIMIT_MS`:
the longest cycle period less what the controller is not to blame for (drivers/loop_times.py: the
cycling thread waiting on a run queue, a stopped CPU, an in-process simulator holding the GIL).
A late device reply does not count: the loop ran on time. The rule holds for every build, run
alone or beside other test workers.
"""
from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

OWN_PERIOD_LIMIT_MS = 30.0
CYCLIC = ("power_source", "cellio")


def link_rows(journal: Path) -> list[tuple[int, list[dict[str, object]]]]:
    """(run, links) of every `links` row of a journal, read-only."""
    con = sqlite3.connect(f"file:{journal}?mode=ro", uri=True, timeout=5.0)
    try:
        rows = con.execute("SELECT run, message FROM events WHERE kind='links' ORDER BY id").fetchall()
    except sqlite3.Error:
        return []
    finally:
        con.close()
    out = []
    for run, msg in rows:
        try:
            out.append((int(run), list(json.loads(msg))))
        except (TypeError, ValueError):
            continue
    return out


def late_cycles(journal: Path, rows: list[tuple[int, list[dict[str, object]]]]) -> list[str]:
    """One line per cyclic link whose controller-caused period is over the limit."""
    out = []
    for run, links in rows:
        for ln in links:
            own = ln.get("max_own_period_ms")
            if ln.get("device") in CYCLIC and isinstance(own, (int, float)) and own > OWN_PERIOD_LIMIT_MS:
                out.append(f"{journal.parent.name} run {run}: {ln['device']} max_period_ms {ln.get('max_period_ms')}, "
                           f"{own} ms of it the controller's (the OS's share {ln.get('os_delay_ms')} ms, the in-process "
                           f"simulators' {ln.get('device_delay_ms')} ms; limit {OWN_PERIOD_LIMIT_MS:g} ms)")
    return out


class JournalWatch:
    """The journals seen so far in one test process, with how many `links` rows each was checked for."""

    def __init__(self) -> None:
        self.seen: dict[Path, int] = {}

    def new_late(self, root: Path) -> list[str]:
        """Late cycles in the `links` rows written under `root` since the last call."""
        out: list[str] = []
        for d, _dirs, files in os.walk(root):
            if "journal.sqlite" not in files:
                continue
            path = Path(d) / "journal.sqlite"
            rows = link_rows(path)
            new = rows[self.seen.get(path, 0):]
            self.seen[path] = len(rows)
            out += late_cycles(path, new)
        return out
