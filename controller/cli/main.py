"""`cell`: the command line. Each subcommand group lives in its own module with `register()`."""
from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import logging
import math
import sys
from typing import Any, Sequence

from controller.cli import outcome
from controller.cli.parsing import Parser
from core.errors import CellError, Fault

# Subcommand modules, imported lazily so that `cell process` does not pay for Textual or
# pymodbus. Each module defines `register(subparsers)` which adds its parser(s) and sets
# `func=handler` where `handler(args) -> int`.
COMMANDS: dict[str, str] = {
    "process": "controller.cli.process",
    "bead": "controller.cli.bead",
    "plan": "controller.cli.plan",
    "align": "controller.cli.align",
    "sim": "controller.cli.sim",
    "run": "controller.cli.run",
    "resume": "controller.cli.run",
    "demo": "controller.cli.demo",
    "tui": "controller.cli.tui",
    "docs": "controller.cli.docs",
    "export": "controller.cli.export",
    "journal": "controller.cli.journal",
    "repair": "controller.cli.repair",
    "finish": "controller.cli.finish",
    "report": "controller.cli.report",
    "runs": "controller.cli.report",
    "records": "controller.cli.records",
}


EPILOG = """exit status (docs/controller.md, "Exit codes"):
  0    complete              1    stopped by a fault, E-stop or abort (a journal write that failed too)
  2    bad input, an unreachable device, a cell in use by another controller, a firmware lacking axes
  3    complete with defects
  130 / 143 / 129   stopped by SIGINT / SIGTERM / SIGHUP: weld start dropped, motion held (CNC safe stop),
                    the cause journaled; `cell resume` continues (a second signal is noted, not obeyed)

one controller per cell: run, resume, demo, tui, align run and repair run hold an exclusive lock
named after the cell ($CELL_LOCK_DIR, else $XDG_RUNTIME_DIR/cell, else /tmp/cell-UID)."""


def emit_json(obj: Any) -> None:
    """Print exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(_finite(obj), sort_keys=False, allow_nan=False) + "\n")
    sys.stdout.flush()
    outcome.emitted()


def _fail(message: str, code: int, state: str | None = None) -> int:
    """One `error:` line on stderr (the `--json` object carries it too); the exit code."""
    sys.stderr.write(message + "\n")
    outcome.error(message, state)
    return code


def _finite(obj: Any) -> Any:
    """The object with every NaN/inf float as null: `--json` output is always valid JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    parser = Parser(prog="cell", description="Cell controller for metal additive manufacturing.", epilog=EPILOG,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    wanted = None
    if argv:
        first = next((a for a in argv if not a.startswith("-")), None)
        if first in COMMANDS:
            wanted = COMMANDS[first]
    seen: set[str] = set()
    for module in COMMANDS.values():
        if module in seen:
            continue
        seen.add(module)
        if wanted is not None and module != wanted:
            # Only the needed module is imported, and no placeholder parser for the others (each
            # costs argparse's translation lookups): the command named is the one parsed.
            continue
        command = importlib.import_module(module)  # a missing command module is an error, never skipped
        command.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """`cell`: the exit code; with `--json`, exactly one JSON object on stdout whatever the path
    (controller/cli/outcome.py)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    outcome.reset()
    code = _main(argv)
    if "--json" in argv and not outcome.has_emitted() and code != 0:
        try:
            emit_json(outcome.fallback(code))
        except OSError:
            pass
    return code


def _main(argv: list[str]) -> int:
    # trimesh logs its parsers' tracebacks while it tries the next format: the user gets the
    # planner's one `error:` line instead
    logging.getLogger("trimesh").setLevel(logging.CRITICAL)
    try:
        with _early_lock(argv):  # one controller per cell: refused before the heavy imports
            parser = build_parser(argv)
            args = parser.parse_args(argv)
            return int(args.func(args) or 0)
    except CellError as exc:
        return _fail(f"error: {exc}", outcome.code_for(exc), exc.state if isinstance(exc, Fault) else None)
    except UnicodeDecodeError as exc:
        return _fail(f"error: {_named(exc)}: not UTF-8 text (byte {exc.start}: {exc.reason}); "
                     "save the file as UTF-8", 2)
    except RecursionError:
        return _fail("error: an input file is nested too deeply to read; give a flat file", 2)
    except _journal_errors() as exc:
        return _fail(f"error: a journal could not be read ({_short(exc)}); it was left untouched: "
                     "`cell journal check RUN_DIR` says what is readable", 2)
    except MemoryError:
        return _fail("error: an input is too large to process in memory; give a smaller one", 2)
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):
            return 0
        where = f"{exc.filename}: " if exc.filename else ""
        return _fail(f"error: {where}{exc.strerror or exc}; check the path", 2)
    except SystemExit as exc:  # argparse's usage error (already one `error:` line) or --help
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except KeyboardInterrupt:
        return _fail("error: interrupted", 130)
    except (ValueError, TypeError, ArithmeticError, KeyError, IndexError) as exc:
        # the last line of defence of the contract: bad input that slipped past a validator
        # is still one `error:` line and exit 2, never a traceback
        return _fail(f"error: bad input ({type(exc).__name__}: {_short(exc)})", 2)


def _journal_errors() -> type[Exception] | tuple[()]:
    """sqlite3.DatabaseError once a journal was opened; nothing to catch (and no import) before."""
    sqlite3 = sys.modules.get("sqlite3")
    return sqlite3.DatabaseError if sqlite3 is not None else ()


def _early_lock(argv: list[str]) -> contextlib.AbstractContextManager[object]:
    """cell_lock.early(argv); `cell plan` touches no device and holds no lock: it skips the import."""
    if next((a for a in argv if not a.startswith("-")), None) == "plan":
        return contextlib.nullcontext()
    # every other command: cell_lock.early decides which ones lock (plan's start-up skips its imports)
    from controller.api.lock import early

    return early(argv)


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text[:300] + ("..." if len(text) > 300 else "")


def _named(exc: UnicodeDecodeError) -> str:
    """The file being read when the decode failed (from the traceback's frames), else 'input'."""
    tb = exc.__traceback__
    name = None
    while tb is not None:
        loc = tb.tb_frame.f_locals
        for key in ("path", "p", "csv_path", "filename", "file"):
            v = loc.get(key)
            if isinstance(v, (str, bytes)) or hasattr(v, "__fspath__"):
                name = str(v)
                break
        tb = tb.tb_next
    return name or "input"


if __name__ == "__main__":
    raise SystemExit(main())
