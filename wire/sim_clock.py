"""The simulators' clock line: how a command asks `cell sim up` for the time scale it can feed.

Not a device protocol: real devices have no clock to set, and nothing here travels on a device's
link. `cell sim up` serves it on `cell.sim_clock_url` (docs/controller.md, "Simulated time the
host can feed"). One ASCII line each way:

    SCALE?          ->  SCALE 60
    SCALE 10        ->  SCALE 10         (the simulators run at 10 from now on)
    INJECT cellio door_open 0.5  ->  OK  (a seeded fault now, for 0.5 wall seconds; sims/inject.py)
    INJECT cellio door_open      ->  OK  (until it is undone: door_close)
    anything else   ->  ERR <why>

The INJECT line is the simulators' side of `Simulators.inject` (tests and `cell run --fault`
against `cell sim up`): an operator opening the door, an arc loss. Nothing of it reaches a
device's link either.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

MAX_SCALE = 1000.0


def ask(scale: float | None) -> bytes:
    """The request: set `scale`, or (None) ask for the current one."""
    return b"SCALE?\n" if scale is None else f"SCALE {scale:g}\n".encode()


@dataclass(frozen=True)
class Inject:
    """An INJECT request: `fault` now on `device`'s simulator, for `duration_s` (None: no end given)."""

    device: str
    fault: str
    duration_s: float | None = None

    def line(self) -> bytes:
        tail = "" if self.duration_s is None else f" {self.duration_s:g}"
        return f"INJECT {self.device} {self.fault}{tail}\n".encode()


OK = b"OK\n"


def _parse_inject(args: str) -> Inject | str:
    parts = args.split()
    if len(parts) not in (2, 3):
        return "send INJECT <device> <fault> [<seconds>]"
    try:
        dur = float(parts[2]) if len(parts) == 3 else None
    except ValueError:
        return f"duration {parts[2][:20]!r} is not a number"
    if dur is not None and not dur >= 0.0:
        return f"duration {dur:g} is negative"
    return Inject(parts[0], parts[1], dur)


def parse_request(line: bytes) -> float | None | Inject | str:
    """A request line -> the scale to set, None (a question), a fault to inject or an error text."""
    text = line.decode("ascii", "replace").strip()
    if text == "SCALE?":
        return None
    word, _, value = text.partition(" ")
    if word == "INJECT":
        return _parse_inject(value)
    if word != "SCALE":
        return f"unknown request {text[:40]!r}; send SCALE?, SCALE <k> or INJECT <device> <fault> [<s>]"
    try:
        k = float(value)
    except ValueError:
        return f"time scale {value[:20]!r} is not a number"
    if not 0.0 < k <= MAX_SCALE:
        return f"time scale {k:g} is outside (0, {MAX_SCALE:g}]"
    return k


def answer(scale: float) -> bytes:
    return f"SCALE {scale:g}\n".encode()


def error(why: str) -> bytes:
    return f"ERR {why}\n".encode()


def parse_ok(line: bytes) -> None:
    """The answer to an INJECT: OK, else ValueError with the simulators' words."""
    text = line.decode("ascii", "replace").strip()
    if text != "OK":
        word, _, value = text.partition(" ")
        raise ValueError(value if word == "ERR" else f"unexpected answer {text[:60]!r}")


def parse_answer(line: bytes) -> float:
    """The simulators' answer -> their time scale; ValueError with their words otherwise."""
    text = line.decode("ascii", "replace").strip()
    word, _, value = text.partition(" ")
    if word == "SCALE":
        return float(value)
    raise ValueError(value if word == "ERR" else f"unexpected answer {text[:60]!r}")


def clock_file(directory: Path, cnc_url: str) -> Path:
    """Where the `cell sim up` serving the CNC at `cnc_url` writes its clock's address
    (`{"pid", "url", "cnc"}`): the runtime directory of core/runtime_dir.py."""
    safe = "".join(c if c.isalnum() else "_" for c in cnc_url)
    return directory / f"sim-clock-{safe}.json"
