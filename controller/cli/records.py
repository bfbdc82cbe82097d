"""`cell records sync [--url URL]` and `cell records query ...`: the shop's record store
(docs/contract.md §9, docs/records.md).

- `sync`: send every record queued in the runs directory (`records.pending.json`); a run whose
  record was never written gets it from its journal first. Exit 0 when nothing stays queued,
  1 when the store could not take every record (each keeps its queue file and the reason).
- `query`: builds (or, with `--defects`, beads with a defect) by material, wire lot, cell and
  date, with arc time and heat input per part; `--csv FILE` writes the rows, `--json` prints them.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any
from controller.cli.parsing import Subcommands


def register(sub: Subcommands) -> None:
    p = sub.add_parser("records", help="the shop's record store: send queued records, query builds and beads")
    rs = p.add_subparsers(dest="records_command", metavar="SUBCOMMAND")
    rs.required = True
    s = rs.add_parser("sync", help="send every record queued in the runs directory to the record store")
    _common(s)
    s.add_argument("--runs", metavar="DIR", help="runs directory (default: cell.yaml's runs_dir)")
    s.set_defaults(func=_sync)
    q = rs.add_parser("query", help="builds, or beads with defects, by material, wire lot, cell and date")
    _common(q)
    q.add_argument("--defects", action="store_true", help="beads with a defect instead of builds")
    q.add_argument("--material", metavar="M", help="the job's material (e.g. inconel718-1.0mm)")
    q.add_argument("--wire-lot", metavar="L", help="the wire lot")
    q.add_argument("--cell", metavar="C", help="the cell's name (cell.yaml cell.name)")
    q.add_argument("--since", metavar="DATE", help="builds started on or after DATE (ISO 8601; UTC unless an offset is given)")
    q.add_argument("--limit", type=int, default=10000, metavar="N", help="at most N rows (default 10000)")
    q.add_argument("--csv", metavar="FILE", help="write the rows as CSV")
    q.set_defaults(func=_query)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--url", metavar="URL", help="the store (default cell.yaml's records.url): sqlite:///PATH or "
                                                "postgresql://USER@HOST:PORT/DB")
    p.add_argument("--cell-config", metavar="FILE", help="cell config (default config/cell.yaml)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _url(args: argparse.Namespace, need_config: bool = True) -> tuple[str, Any]:
    """The store's URL (--url, else cell.yaml's records.url) and cell.yaml (None when --url is given
    and the command needs nothing else of it: `query` answers without loading the config schema)."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from core.errors import InputError

    cfg = None
    if need_config or not args.url:
        # lazy: the config schema (pydantic) only when cell.yaml is read
        from core.config import load_cell

        cfg = load_cell(args.cell_config)
    url = args.url or (cfg.records.url if cfg is not None else None)
    if not url:
        raise InputError("no record store: give --url sqlite:///PATH or postgresql://..., or records.url in cell.yaml")
    if not url.startswith(("sqlite:///", "postgresql://", "postgres://")):
        raise InputError(f"--url {url!r}: expected sqlite:///PATH or postgresql://USER@HOST:PORT/DB")
    return url, cfg


def _sync(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.records import redact, sync_records
    from controller.cli.main import emit_json

    url, cfg = _url(args)
    runs = Path(args.runs or cfg.cell.runs_dir)
    res = sync_records(runs, url, cell=cfg.cell.name, timeout_s=cfg.records.connect_timeout_s)
    out = {"url": redact(url), "runs_dir": str(runs), **res.as_dict()}
    if args.json:
        emit_json(out)
    else:
        print(f"records: {out['sent']} sent, {out['unchanged']} already in the store, {out['queued']} still queued "
              f"({redact(url)})")
        for e in out["errors"]:
            print(f"  {e}")
    return 1 if out["queued"] else 0


def _query(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    import csv
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.api.records import Filters, query_records, redact, since_arg
    from core.errors import InputError

    url, cfg = _url(args, need_config=False)
    if args.limit < 1:
        raise InputError(f"--limit {args.limit}: give a positive number of rows")
    f = Filters(material=args.material, wire_lot=args.wire_lot, cell=args.cell,
                since=since_arg(args.since) if args.since else None, limit=args.limit)
    rows = query_records(url, f, defects=args.defects,
                         timeout_s=cfg.records.connect_timeout_s if cfg is not None else 5.0)
    kind = "beads" if args.defects else "builds"
    if args.csv:
        cols = list(rows[0]) if rows else []
        try:
            with open(args.csv, "w", newline="", encoding="utf-8") as fh:
                w = csv.DictWriter(fh, fieldnames=cols)
                w.writeheader()
                w.writerows(rows)
        except OSError as exc:
            raise InputError(f"--csv {args.csv}: cannot write ({exc.strerror or exc})") from None
    if args.json:
        emit_json({"url": redact(url), "kind": kind, "count": len(rows), "rows": rows,
                   "csv": args.csv, "truncated": len(rows) >= args.limit})
        return 0
    _print_rows(kind, rows)
    return 0


def _print_rows(kind: str, rows: list[dict[str, Any]]) -> None:
    if not rows:
        print(f"no {kind}")
        return
    for r in rows:
        if kind == "builds":
            print(f"{r['started'] or '-'}  {r['cell']}  {r['job_name']}  {r['material']}  lot {r['wire_lot'] or '-'}  "
                  f"{r['state']}  arc {r['arc_time_s'] or 0:.1f} s  heat {r['heat_input_kj'] or 0:.1f} kJ  "
                  f"defects {r['bead_defects'] or 0}")
        else:
            print(f"{r['started'] or '-'}  {r['cell']}  {r['job_name']}  lot {r['wire_lot'] or '-'}  layer {r['layer']} "
                  f"pass {r['pass']}: {r['defect_reasons'] or r['defects_count']}")
    print(f"{len(rows)} {kind}")
