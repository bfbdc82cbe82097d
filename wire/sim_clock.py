"""The simulators' clock line: how a command asks `cell sim up` for the time scale it can feed.

Not a device protocol: real devices have no clock to set, and nothing here travels on a device's
link. `cell sim up` serves it on `cell.sim_clock_url` (docs/controller.md, "Simulated time the
host can feed"). One ASCII line each way:

    SCALE?          ->  SCALE 60
    SCALE 10        ->  SCALE 10         (the simulators run at 10 from now on)
    anything else   ->  ERR <why>
"""
from __future__ import annotations

from pathlib import Path

MAX_SCALE = 1000.0


def ask(scale: float | None) -> bytes:
    """The request: set `scale`, or (None) ask for the current one."""
    return b"SCALE?\n" if scale is None else f"SCALE {scale:g}\n".encode()


def parse_request(line: bytes) -> float | None | str:
    """A request line -> the scale to set, None (a question) or an error text."""
    text = line.decode("ascii", "replace").strip()
    if text == "SCALE?":
        return None
    word, _, value = text.partition(" ")
    if word != "SCALE":
        return f"unknown request {text[:40]!r}; send SCALE? or SCALE <k>"
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
