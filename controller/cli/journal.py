"""`cell journal check RUN_DIR`: what of a build's journal is readable, without writing to it.

Exit status: 0 the journal is healthy, 1 it is damaged (the report says what is still readable),
2 bad input (no such run directory, no journal there).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from controller.cli.parsing import Subcommands
from core.errors import InputError


def register(sub: Subcommands) -> None:
    p = sub.add_parser("journal", help="inspect a build's journal (read-only)")
    jsub = p.add_subparsers(dest="journal_command", metavar="ACTION", parser_class=type(p))
    jsub.required = True
    c = jsub.add_parser("check", help="say what of RUN_DIR/journal.sqlite is readable (never writes to it)")
    c.add_argument("run_dir", metavar="RUN_DIR", help="run directory (or the journal file itself)")
    c.add_argument("--json", action="store_true", help="print the findings as one JSON object")
    c.set_defaults(func=_check)
    r = jsub.add_parser("recover", help="copy what a damaged journal proves into a new run directory to resume")
    r.add_argument("run_dir", metavar="RUN_DIR", help="run directory of the damaged journal (left untouched)")
    r.add_argument("--job", default=None, metavar="JOB", help="the job file, when the journal's job record is lost")
    r.add_argument("--out", default=None, metavar="DIR", help="the new run directory (default RUN_DIR-recovered)")
    r.add_argument("--json", action="store_true", help="print the result as one JSON object")
    r.set_defaults(func=_recover)


def _journal_path(arg: str) -> Path:
    p = Path(arg)
    if p.is_dir():
        p = p / "journal.sqlite"
    elif not p.exists():
        raise InputError(f"{p}: no such run directory; check the path")
    if not p.exists() and not p.with_name(p.name + "-wal").exists():
        raise InputError(f"{p.parent}: no journal.sqlite here; nothing to check")
    return p


def _check(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.api.runs import check_journal

    h = check_journal(_journal_path(args.run_dir))
    out = {
        "journal": str(h.path), "state": "healthy" if h.damage is None else "damaged", "damage": h.damage,
        "bytes": h.path.stat().st_size if h.path.exists() else None, "wal_bytes": h.wal_bytes,
        "readable": h.readable, "job_hash": h.job_hash, "job_checksum_ok": h.job_hash_ok,
        "passes_done": h.passes_done,
        "last_done": {"layer": h.last_done[0], "pass": h.last_done[1]} if h.last_done else None,
    }
    if args.json:
        emit_json(out)
    else:
        w = sys.stdout.write
        w(f"journal {h.path}: {out['state']}" + (f" ({h.damage})" if h.damage else "") + "\n")
        w(f"  {out['bytes']} bytes, WAL {h.wal_bytes} bytes\n")
        if h.readable:
            w("  readable rows: " + ", ".join(f"{k} {v}" for k, v in h.readable.items()) + "\n")
        else:
            w("  no table is readable\n")
        if h.job_hash is not None:
            ok = {True: "matches", False: "DOES NOT match", None: "unknown"}[h.job_hash_ok]
            w(f"  job {h.job_hash[:12]}: the stored job {ok} its checksum\n")
        if h.passes_done is not None:
            last = f"; last done: layer {h.last_done[0]}, pass {h.last_done[1]}" if h.last_done else ""
            w(f"  passes journaled done: {h.passes_done}{last}\n")
        if h.damage:
            w("  the file was not modified; keep it (and its -wal) for recovery\n")
    return 0 if h.damage is None else 1


def _recover(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.api.jobs import read_job
    from controller.api.runs import recover_journal

    src = _journal_path(args.run_dir)
    run_dir = src.parent
    out = Path(args.out) if args.out else run_dir.with_name(run_dir.name + "-recovered")
    job = read_job(args.job) if args.job else None
    res = recover_journal(run_dir, out, job)
    d = {"run_dir": str(res.run_dir), "rows": res.rows, "lost_chunks": res.lost_chunks,
         "passes_done": res.passes_done, "next": f"cell resume {res.run_dir}"}
    if args.json:
        emit_json(d)
    else:
        sys.stdout.write(f"recovered into {res.run_dir}: {res.passes_done} passes proven done; "
                         f"rows {res.rows}" + (f"; chunks lost {res.lost_chunks}" if res.lost_chunks else "")
                         + f"\n{src} was left untouched; continue with `cell resume {res.run_dir}`\n")
    return 0
