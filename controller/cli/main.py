"""`cell`: the command line. Each subcommand group lives in its own module with `register()`."""
from __future__ import annotations

import argparse
import importlib
import json
import sys
from typing import Any, NoReturn, Sequence

from planner.errors import CellError

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
    "demo": "controller.cli.run",
    "tui": "controller.cli.tui",
    "docs": "controller.cli.docs",
}


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one `error:` line and exit status 2."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"error: {self.prog}: {message} (see `{self.prog} --help`)\n")
        raise SystemExit(2)


def emit_json(obj: Any) -> None:
    """Print exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(obj, sort_keys=False) + "\n")
    sys.stdout.flush()


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    parser = _Parser(prog="cell", description="Cell controller for metal additive manufacturing.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    wanted = None
    if argv:
        first = next((a for a in argv if not a.startswith("-")), None)
        if first in COMMANDS:
            wanted = COMMANDS[first]
    seen: set[str] = set()
    for name, module in COMMANDS.items():
        if module in seen:
            continue
        seen.add(module)
        if wanted is not None and module != wanted:
            # Only the needed module is imported; the others get a placeholder for --help.
            for alias, mod in COMMANDS.items():
                if mod == module:
                    sub.add_parser(alias, add_help=False)
            continue
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name == module:
                continue  # not built yet
            raise
        mod.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser(argv)
        args = parser.parse_args(argv)
        return int(args.func(args) or 0)
    except CellError as exc:
        sys.stderr.write(f"error: {exc}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted\n")
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
