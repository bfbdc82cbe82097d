"""A command-line build that pauses says why and how to go on, and takes the answer from the same
terminal (`cell run`, `cell resume`, `cell demo`; docs/closed-loop.md "When the build pauses").

The layer loop pauses a build before a layer whose stick-out left the safe window, or whose
correction is out of bounds; the operator's pause does the same at the end of a bead. The prompt
prints the reason and the two ways on:

    paused before layer 37: one bead's stick-out reads 11.70 mm, outside the window [12, 18] ...
      r + Enter: resume the build here;  s + Enter: stop (the journal keeps it: `cell resume RUN_DIR` later)

and reads the answer from stdin on a thread of its own (a daemon: a build that ends while it waits
is not held up by it). When stdin ends (not a terminal: /dev/null, a closed pipe) nobody can
answer: the build is stopped the same way, never left waiting forever, and the line says so. A
pipe can answer (`echo r | cell run ...`).
"""
from __future__ import annotations

import asyncio
import sys
import threading
from typing import Any, Callable, TextIO

RESUME = ("r", "resume", "c", "continue", "go")
STOP = ("s", "stop", "q", "quit", "abort")


class PausePrompt:
    """Subscribed to the controller's snapshots: on `paused`, ask once, act on the answer."""

    def __init__(self, ctl: Any, say: Callable[[str], None], stream: TextIO | None = None) -> None:
        self.ctl, self.say = ctl, say
        self.stream = stream if stream is not None else sys.stdin
        self.loop = asyncio.get_running_loop()
        self._asking = False
        self.answers: list[str] = []     # what was answered (the tests read it)
        self._unsub = ctl.subscribe(self._snap)

    def close(self) -> None:
        self._unsub()

    def _snap(self, snap: Any) -> None:
        if snap.state == "paused" and not self._asking:
            self._asking = True
            why = snap.alarms[-1].message if snap.alarms else "paused at the end of a bead (operator)"
            self.loop.call_soon_threadsafe(self._ask, why)

    def _ask(self, why: str) -> None:
        run_dir = getattr(self.ctl, "run_dir", None) or "RUN_DIR"
        self.say(f"paused: {why}")
        self.say(f"  r + Enter: resume the build here;  s + Enter: stop (the journal keeps it: `cell resume {run_dir}` "
                 "continues it later)")
        threading.Thread(target=self._read, name="pause-prompt", daemon=True).start()

    def _read(self) -> None:
        """On its own thread: lines until one is an answer; None at the end of stdin."""
        try:
            is_tty = self.stream.isatty()
        except (AttributeError, ValueError):
            is_tty = False
        while True:
            try:
                line = self.stream.readline()
            except (OSError, ValueError):
                line = ""
            if not line:
                self.loop.call_soon_threadsafe(self._act, None, is_tty)
                return
            word = line.strip().lower()
            if word in RESUME or word in STOP:
                self.loop.call_soon_threadsafe(self._act, word, is_tty)
                return
            self.loop.call_soon_threadsafe(self.say, f"  '{line.strip()}'? type r (resume) or s (stop), then Enter")

    def _act(self, word: str | None, is_tty: bool) -> None:
        self.answers.append(word or "")
        run_dir = getattr(self.ctl, "run_dir", None) or "RUN_DIR"
        try:
            if word in RESUME:
                self.say("resuming")
                self.ctl.resume()
            else:
                if word is None:
                    where = "the terminal closed" if is_tty else "stdin is not a terminal and has ended"
                    self.say(f"  no answer possible ({where}): stopping the build")
                self.say(f"stopping; `cell resume {run_dir}` continues it from the journal")
                self.ctl.abort()
        except Exception as exc:   # the build ended meanwhile (a fault, a signal): nothing left to answer
            self.say(f"  ({exc})")
        finally:
            self._asking = False
