"""`cell docs`: regenerate generated documentation (the state-machine diagram)."""
from __future__ import annotations

import argparse
from pathlib import Path

from controller.cli.parsing import Subcommands
from controller.api.offline import state_machine_doc

DOCS = Path(__file__).resolve().parents[2] / "docs"


def register(sub: Subcommands) -> None:
    p = sub.add_parser("docs", help="regenerate docs/state-machine.md from the controller's state machine")
    p.add_argument("--out", default=str(DOCS), metavar="DIR", help="docs directory (default docs/)")
    p.add_argument("--check", action="store_true", help="exit 1 when the file is stale instead of writing it")
    p.set_defaults(func=_docs)


def _docs(args: argparse.Namespace) -> int:
    path = Path(args.out) / "state-machine.md"
    text = state_machine_doc()
    current = path.read_text(encoding="utf-8") if path.exists() else None
    if args.check:
        if current != text:
            print(f"{path} is stale: run `cell docs`")
            return 1
        print(f"{path} is up to date")
        return 0
    if current != text:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path}")
    else:
        print(f"{path} is up to date")
    return 0
