"""The CNC simulator's seeded `freeze` fault (sims/faults.py): a machine that reports Run with
lines queued and never moves. `freeze@t=T` (wall seconds since start), `@move=N` (once N blocks
executed), `@travel=N` (the N-th rapid `G0` never starts), `@probe=N` (the N-th probing move never
starts: a probe move that never ends), `@home=N` (the N-th homing cycle never finishes). Once on,
it stays on."""
from __future__ import annotations

import time
from collections.abc import Callable

from sims.cnc.block import Block


class Freeze:
    """The fault's state; `executed()` counts the blocks the simulator has executed."""

    def __init__(self, executed: Callable[[], int]) -> None:
        self.executed = executed
        self.when: tuple[str, float] | None = None
        self.frozen = False
        self.t0 = time.monotonic()
        self._starts: dict[str, int] = {}   # travel and probing moves come up, homing cycles begun
        self._counted = -1                  # the latest block counted

    def on(self, head: Block | None) -> bool:
        """Checked before the executor moves: whether the machine stands (`head`: the next motion block)."""
        if self.when is None or self.frozen:
            return self.frozen
        cond, n = self.when
        if cond == "t":
            self.frozen = time.monotonic() - self.t0 >= n
        elif cond == "move":
            self.frozen = self.executed() >= n
        elif head is not None:
            self.starting(head)
        return self.frozen

    def starting(self, b: Block) -> bool:
        """Block `b` is about to start: True when `@travel=N` / `@probe=N` stops it there."""
        if self.frozen or self.when is None or self.when[0] not in ("travel", "probe"):
            return self.frozen
        cond, n = self.when
        if not b.started and b.seq != self._counted:
            self._counted = b.seq
            if (b.verb == "G0") if cond == "travel" else bool(b.probe):
                self._starts[cond] = self._starts.get(cond, 0) + 1
                self.frozen = self._starts[cond] >= n
        return self.frozen

    def homing(self) -> bool:
        """A homing cycle begins: True when `@home=N` makes it never finish."""
        self._starts["home"] = self._starts.get("home", 0) + 1
        if self.when is not None and self.when[0] == "home" and self._starts["home"] >= self.when[1]:
            self.frozen = True
        return self.frozen and self.when is not None and self.when[0] == "home"
