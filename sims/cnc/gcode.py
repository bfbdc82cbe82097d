"""The CNC simulator's G-code interpreter: one line into planner blocks, as grbl 1.1h does it.

A line is split into words (`split_words`), its G and M words looked up in the tables `G_CODES`
and `M_CODES` (a code in neither is `error:20`: arcs, G10/G28/G30/G92, G38.4/5 are not
simulated), the words checked, the modal state updated in grbl's order of execution, and the
blocks queued on the simulator's planner (`run_gcode`). Probing (G38.2/G38.3) waits for the
move and answers the `[PRB:...]` line (`probe_cycle`). The modal state, the parser's position and
the planner are the shared `CncState` (state.py).
"""
from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from dataclasses import dataclass

from sims.cnc.block import NUMBER, Block, GrblError, Pos5, pos5
from sims.cnc.state import CncParts
from wire.grbl_protocol import format_probe


@dataclass
class LineModes:
    """What one line's G words set (starting from the modal state in effect)."""

    inverse: bool
    absolute: bool
    inches: bool
    motion: str | None = None
    dwell: bool = False
    machine: bool = False
    tlo: str | None = None     # "set" (G43.1 Z…) | "clear" (G49)


def _g_motion(m: LineModes, code: float) -> None:
    if m.motion is not None:
        raise GrblError(21)
    m.motion = {0: "G0", 1: "G1", 38.2: "G38.2", 38.3: "G38.3", 80: "G80"}[code]


def _g_dwell(m: LineModes, code: float) -> None:
    m.dwell = True


def _g_machine(m: LineModes, code: float) -> None:
    m.machine = True


def _g_distance(m: LineModes, code: float) -> None:
    m.absolute = code == 90


def _g_units(m: LineModes, code: float) -> None:
    m.inches = code == 20


def _g_feed_mode(m: LineModes, code: float) -> None:
    m.inverse = code == 93


def _g_tlo(m: LineModes, code: float) -> None:
    m.tlo = "set" if code == 43.1 else "clear"


def _g_accepted(m: LineModes, code: float) -> None:
    pass  # accepted; the simulator keeps G54 with zero offsets


G_CODES: dict[float, Callable[[LineModes, float], None]] = {
    **dict.fromkeys((0, 1, 38.2, 38.3, 80), _g_motion),
    4: _g_dwell,
    53: _g_machine,
    **dict.fromkeys((90, 91), _g_distance),
    **dict.fromkeys((20, 21), _g_units),
    **dict.fromkeys((93, 94), _g_feed_mode),
    **dict.fromkeys((43.1, 49), _g_tlo),
    **dict.fromkeys((17, 40, 54, 55, 56, 57, 58, 59, 61, 91.1), _g_accepted),
}
# M word -> spindle on (M3/M4) / off (M5), or None: accepted without effect
M_CODES: dict[int, bool | None] = {3: True, 4: True, 5: False, **dict.fromkeys((0, 1, 2, 30, 7, 8, 9), None)}


def split_words(line: str) -> tuple[dict[str, float], list[float], list[int]]:
    """(words by letter, G values, M values) of an upper-case line without spaces or comments."""
    words: dict[str, float] = {}
    gs: list[float] = []
    ms: list[int] = []
    i = 0
    while i < len(line):
        letter = line[i]
        if not "A" <= letter <= "Z":
            raise GrblError(1)
        m = NUMBER.match(line, i + 1)
        if m is None:
            raise GrblError(2)
        val = float(m.group(0))
        i = m.end()
        if letter == "G":
            gs.append(val)
        elif letter == "M":
            if val != int(val):
                raise GrblError(20)
            ms.append(int(val))
        else:
            if letter in words:
                raise GrblError(25)
            words[letter] = val
    return words, gs, ms


def _spindle(ms: list[int]) -> bool | None:
    spindle: bool | None = None
    for mc in ms:
        if mc not in M_CODES:
            raise GrblError(20)
        if M_CODES[mc] is not None:
            spindle = M_CODES[mc]
    return spindle


def _spindle_block(seq: int, line: str, on: bool, ms: list[int], s: float) -> Block:
    """The spindle / laser block of a line: M3, M4 (sims/cnc/laser.py: dynamic power) or M5."""
    ccw = on and 4 in ms
    return Block(seq, ("M4" if ccw else "M3") if on else "M5", line, s=s, spindle=on, ccw=ccw)


def _check_words(words: dict[str, float], letters: str, dwell: bool) -> None:
    for letter in words:
        if letter not in letters + "FSPT":
            raise GrblError(20)
    if "F" in words and words["F"] < 0 or "S" in words and words["S"] < 0:
        raise GrblError(4)
    if "P" in words and not dwell:
        raise GrblError(36)
    if dwell and "P" not in words:
        raise GrblError(28)


def _set_modal(sim: CncParts, modes: LineModes, words: dict[str, float]) -> float:
    """The modal updates, in grbl's order of execution; the unit factor (mm per unit)."""
    sim.machine.absolute, sim.machine.inches = modes.absolute, modes.inches
    if modes.inverse != sim.machine.inverse_time:
        sim.machine.inverse_time = modes.inverse
        sim.machine.feed_rate = 0.0  # grbl: switching feed modes leaves the feed undefined
    unit = 25.4 if modes.inches else 1.0
    if "F" in words:
        sim.machine.feed_rate = words["F"] * (1.0 if modes.inverse else unit)
    if "S" in words:
        sim.machine.s_word = words["S"]
    if modes.motion is not None:
        sim.machine.motion_mode = modes.motion
    return unit


def _tool_words(sim: CncParts, modes: LineModes, words: dict[str, float], unit: float) -> None:
    """`T<n>` selects a tool (M0, the operator, loads it: grbl 1.1h has no M6); `G43.1 Z…` sets the
    dynamic tool length offset (its Z word is no move), `G49` clears it."""
    if "T" in words:
        sim.spindle.selected = int(words["T"])
    if modes.tlo == "set":
        if "Z" not in words:
            raise GrblError(37)
        sim.machine.tlo = words.pop("Z") * unit
    elif modes.tlo == "clear":
        sim.machine.tlo = 0.0


async def run_gcode(sim: CncParts, line: str) -> list[str]:
    """Execute one G-code line: the lines to print before `ok`; GrblError for `error:N`."""
    words, gs, ms = split_words(line)
    nline = words.pop("N", None)
    seq = int(nline) if nline is not None else sim.machine.lines_received

    modes = LineModes(inverse=sim.machine.inverse_time, absolute=sim.machine.absolute, inches=sim.machine.inches)
    for g in gs:
        code = round(g, 1)
        if code not in G_CODES:
            raise GrblError(20)  # arcs, G10/G28/G30/G92, G38.4/5: not simulated
        G_CODES[code](modes, code)
    spindle = _spindle(ms)
    _check_words(words, sim.machine.letters, modes.dwell)

    unit = _set_modal(sim, modes, words)
    _tool_words(sim, modes, words, unit)
    axes = {k: v for k, v in words.items() if k in sim.machine.letters}
    mode = sim.machine.motion_mode
    if spindle is not None:
        sim.machine.push(_spindle_block(seq, line, spindle, ms, sim.machine.s_word))
    if modes.dwell:
        await sim.machine.sync()
        await asyncio.sleep(sim.clock.wall(max(words["P"], 0.0)))
        sim.log_block(Block(seq, "G4", line), sim.clock.now())
    if axes or 0 in ms:
        out = await _move(sim, seq, line, mode, words, axes, modes, unit) if axes else []
        if 0 in ms:   # program pause once the motion before it is done; grbl answers `ok` after `~`
            pause = Block(seq, "M0", line)
            sim.machine.push(pause)
            await sim.machine.wait_for(lambda: pause.done and not sim.machine.hold)
        return out
    if modes.motion is not None and modes.motion.startswith("G38"):
        raise GrblError(26)
    if spindle is None and not modes.dwell:
        sim.machine.push(Block(seq, modes.motion or ("F" if "F" in words else "G"), line))  # modal-only: logged in order
    return []


async def _move(sim: CncParts, seq: int, line: str, mode: str, words: dict[str, float], axes: dict[str, float],
                modes: LineModes, unit: float) -> list[str]:
    """A line with axis words in motion mode `mode` (the modal one in effect): queue the move (or probe)."""
    if mode == "G80":
        raise GrblError(31)
    target = list(sim.machine.gc_pos)
    for k, v in axes.items():
        j = sim.machine.letters.index(k)
        v = v * unit if j < 3 else v
        target[j] = v if (modes.absolute or modes.machine) else target[j] + v
    if "Z" in axes and modes.absolute and not modes.machine:
        target[2] += sim.machine.tlo   # machine Z = programmed Z + the tool length offset
    tgt = pos5(target)
    if mode.startswith("G38"):
        return await probe_cycle(sim, seq, mode, line, tgt)
    if mode == "G1":
        if sim.machine.feed_rate <= 0 or (sim.machine.inverse_time and "F" not in words):
            raise GrblError(22)  # G93: every G1 carries its own F
        feed = sim.machine.feed_rate
        if sim.machine.inverse_time:  # F = 1/minutes for the move: the rate along the 5-D path
            feed = math.dist(tgt, sim.machine.gc_pos) * sim.machine.feed_rate
    else:
        moving = [j for j in range(5) if abs(tgt[j] - sim.machine.gc_pos[j]) > 1e-9]
        feed = min((float(sim.machine.settings[110 + j]) for j in moving), default=float(sim.machine.settings[110]))
    await sim.machine.wait_for(lambda: sim.machine.motion_in_queue < sim.machine.planner_blocks)
    sim.machine.push(Block(seq, mode, line, target=tgt, feed=feed, s=sim.machine.s_word))
    sim.machine.gc_pos = list(tgt)
    return []


async def probe_cycle(sim: CncParts, seq: int, mode: str, line: str, target: Pos5) -> list[str]:
    """G38.2 / G38.3 toward `target`: the `[PRB:...]` line (ALARM:4 / ALARM:5 as grbl raises them)."""
    if sim.machine.feed_rate <= 0:
        raise GrblError(22)
    await sim.machine.sync()
    if all(abs(a - b) < 1e-9 for a, b in zip(target[:3], sim.machine.pos[:3])):
        raise GrblError(33)
    if sim.probe_tripped():
        sim.raise_alarm(4)
        sim.machine.notify()
        return []
    b = Block(seq, mode, line, target=target, feed=sim.machine.feed_rate, s=sim.machine.s_word, probe=mode)
    sim.machine.push(b)
    await sim.machine.wait_for(lambda: b.done)
    sim.machine.gc_pos = list(sim.machine.pos)
    sim.machine.probe_pos = pos5(sim.machine.pos)
    sim.machine.probe_ok = b.contact
    if not b.contact and mode == "G38.2":
        sim.raise_alarm(5)
    return [format_probe(sim.machine.probe_pos, b.contact)]
