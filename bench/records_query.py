"""Query speed of the record store (issue 39): `cell records query --defects --wire-lot L` over
10^6 bead rows, against a PostgreSQL server this bench starts (bench/_postgres.py) and a SQLite file.

    .venv/bin/python -m bench.records_query [--beads 1000000] [--per-build 200] [--lots 50] [--sqlite]

Loads builds of `--per-build` beads each (a defect on every 50th bead, `--lots` wire lots) straight
into the tables (COPY on PostgreSQL, one transaction on SQLite: the rows `send_record` would write,
built by the same functions), then times, five times each:
- the query alone (controller/records/query.py over an open connection);
- the whole command as a user runs it (`cell records query --defects --wire-lot L --json`, a new
  interpreter each time: start-up, connection, query, JSON out).
Prints one JSON object with the figures.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from bench._postgres import running
from bench._records_data import fake_record
from controller.records.db import Store, connect
from controller.records.query import Filters, defective_beads
from controller.records.schema import BEAD_COLUMNS
from controller.records.send import BUILD_COLUMNS, _bead_rows, build_row

ROOT = Path(__file__).resolve().parents[1]


def load(store: Store, n_builds: int, per_build: int, lots: int) -> None:
    """n_builds records of per_build beads into the store, in bulk (made twice, builds first for the
    foreign key: the records are deterministic, and 10^6 bead dicts at once would not fit in memory)."""
    def rec(i: int) -> dict[str, Any]:
        return fake_record(i, beads=per_build, lot=f"LOT-{i % lots:03d}", cell=f"cell-{i % 10:02d}", defect_every=50)

    def builds() -> Iterator[tuple[Any, ...]]:
        for i in range(n_builds):
            r = rec(i)
            yield build_row({**r, "beads": []}, "bench", None)   # the record JSON without its beads (size)

    def beads() -> Iterator[tuple[Any, ...]]:
        for i in range(n_builds):
            r = rec(i)
            yield from _bead_rows(r["build_id"], r)

    bcols, dcols = ", ".join(BUILD_COLUMNS), ", ".join(("build_id", "seq", *BEAD_COLUMNS))
    with store.transaction():
        store.executemany("INSERT INTO cells (name, first_seen, last_seen) VALUES (?, ?, ?) ON CONFLICT (name) "
                          "DO NOTHING", [(f"cell-{k:02d}", "x", "x") for k in range(10)])
        if store.dialect == "postgresql":
            with store.conn.cursor() as cur:
                for table, cols, rows in (("builds", bcols, builds()), ("beads", dcols, beads())):
                    with cur.copy(f"COPY {table} ({cols}) FROM STDIN") as cp:
                        for row in rows:
                            cp.write_row(row)
        else:
            store.conn.executemany(f"INSERT INTO builds ({bcols}) VALUES ({', '.join('?' * len(BUILD_COLUMNS))})",
                                   builds())
            store.conn.executemany(f"INSERT INTO beads ({dcols}) VALUES ({', '.join('?' * (len(BEAD_COLUMNS) + 2))})",
                                   beads())
    if store.dialect == "postgresql":
        store.execute("ANALYZE")


def _times(fn: Any, n: int = 5) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def measure(url: str, lot: str) -> dict[str, Any]:
    st = connect(url)
    try:
        rows = defective_beads(st, Filters(wire_lot=lot))
        alone = _times(lambda: defective_beads(st, Filters(wire_lot=lot)))
        total = st.rows("SELECT count(*) FROM beads")[0][0]
        plan = ([r[0] for r in st.rows("EXPLAIN SELECT 1 FROM builds b JOIN beads d ON d.build_id = b.build_id "
                                       "WHERE b.wire_lot = %s AND d.defects_count > 0", (lot,))]
                if st.dialect == "postgresql" else [])
    finally:
        st.close()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "controller.cli.main", "records", "query", "--defects", "--wire-lot", lot,
           "--url", url, "--json"]

    def cli() -> None:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
        if p.returncode != 0 or json.loads(p.stdout)["count"] != len(rows):
            raise RuntimeError(f"cell records query failed: {p.stderr.strip()[-300:]}")
    whole = _times(cli)
    return {"bead_rows": total, "rows_found": len(rows), "query_s": {"median": round(statistics.median(alone), 4),
            "max": round(max(alone), 4)}, "command_s": {"median": round(statistics.median(whole), 3),
            "max": round(max(whole), 3)}, "plan": plan[:8]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench.records_query")
    ap.add_argument("--beads", type=int, default=1_000_000)
    ap.add_argument("--per-build", type=int, default=200)
    ap.add_argument("--lots", type=int, default=50)
    ap.add_argument("--sqlite", action="store_true", help="also a SQLite file")
    a = ap.parse_args(argv)
    n_builds = max(1, a.beads // a.per_build)
    out: dict[str, Any] = {"builds": n_builds, "beads_per_build": a.per_build, "lots": a.lots,
                           "load": os.getloadavg()[0]}
    with running() as srv:
        url = srv.create_db("bench_query")
        st = connect(url)
        t0 = time.perf_counter()
        load(st, n_builds, a.per_build, a.lots)
        st.close()
        out["postgresql"] = {"load_s": round(time.perf_counter() - t0, 1), **measure(url, "LOT-007")}
    if a.sqlite:
        with tempfile.TemporaryDirectory() as d:
            url = f"sqlite:///{d}/shop.sqlite"
            st = connect(url)
            t0 = time.perf_counter()
            load(st, n_builds, a.per_build, a.lots)
            st.close()
            out["sqlite"] = {"load_s": round(time.perf_counter() - t0, 1), **measure(url, "LOT-007")}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
