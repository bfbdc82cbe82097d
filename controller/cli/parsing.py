"""What the command modules share of argparse: the type of the subcommands action each module's
`register(sub)` adds its parsers to, and the parser the `cell` command and its subcommands use
(a usage error is one `error:` line and exit status 2)."""
from __future__ import annotations

import argparse
import re
import sys
from typing import Any, NoReturn, Protocol

from controller.cli import outcome

# a word such as "-1,-1,-5" (a point, a pivot) or "-0.5"
NEGATIVE_WORD = re.compile(r"^-(\d|\.\d)[\d.,eE+\-]*$")


class Subcommands(Protocol):
    """The subcommands action `add_subparsers()` returns, as `register(sub)` uses it."""

    def add_parser(self, name: str, *, help: str | None = ..., description: str | None = ...) -> argparse.ArgumentParser: ...


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one `error:` line and exit status 2."""

    def error(self, message: str) -> NoReturn:
        line = f"error: {self.prog}: {message} (see `{self.prog} --help`)"
        sys.stderr.write(line + "\n")
        outcome.error(line)
        raise SystemExit(2)


class NumbersParser(Parser):
    """A parser that reads words such as `-1,-1,-5` as values, not options (`--pivot -1,-1,-5`, a
    point `-1,2,3`), as users type them. argparse tells a negative number from an option by its
    `_negative_number_matcher`, which takes only plain numbers: this parser sets its own to
    NEGATIVE_WORD (argparse internals, unchanged since 3.2; no public setting exists)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:   # argparse's own arguments, passed on
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_WORD
        self._has_negative_number_optionals = []
