"""Probe cycles over the CNC driver (docs/contract.md §4): the only part of controller.align with I/O.

One touch point: rapid to a clearance point, `G38.2` fast toward the surface, back off, then
`samples` slow `G38.2` touches from the back-off point; when the samples spread more than the
tolerance the whole point is retried (fast + slow) up to `retries` times. Results are the
latched trip positions `[PRB:…]` in machine coordinates, with the table angles they were taken at.

The work coordinate system is assumed to coincide with the machine's (G54 offset zero): the
cycle commands G90 positions and reads machine positions.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from wire.grbl_protocol import fmt
from controller.align.watched import probing
from controller.ports import ProbePort
from core.config import ProbeSettings
from core.errors import Fault

F = NDArray[np.float64]


class ProbeCycleError(Fault):
    """A probe point failed: no contact, already tripped, not homed, spread above tolerance."""


CncLinkLike = ProbePort  # what the cycle needs of drivers.grbl.CncLink (controller/ports.py)


@dataclass(frozen=True)
class ProbeTarget:
    """Where to touch: a clearance `start` (machine XYZ) and the approach direction (unit)."""

    name: str                    # e.g. "top[4]": named in every error
    start: tuple[float, float, float]
    direction: tuple[float, float, float]
    safe_z: float                # retract height before and after (machine Z)


@dataclass(frozen=True)
class ProbedPoint:
    name: str
    position: F                  # mean of the slow samples, machine XYZ
    samples: F                   # (k, 3) slow trip positions
    spread_mm: float             # max − min of the samples along the approach direction
    attempts: int                # 1 + retries used
    table_deg: tuple[float, float]  # A and B/C when probed
    direction: F


@dataclass
class ProbeLog:
    """What happened, for the report (appended to as the cycle runs)."""

    lines: list[str] = field(default_factory=list)

    def add(self, text: str) -> None:
        self.lines.append(text)


def _xyz(v: Sequence[float] | F) -> str:
    return f"X{fmt(v[0])} Y{fmt(v[1])} Z{fmt(v[2])}"


def _where(t: ProbeTarget) -> str:
    return f"{t.name} (start {fmt(t.start[0])}, {fmt(t.start[1])}, {fmt(t.start[2])}, toward {np.round(t.direction, 4).tolist()})"


async def _rapid(link: CncLinkLike, p: Sequence[float] | F) -> None:
    await link.command(f"G90 G0 {_xyz(p)}")


async def _probe_once(link: CncLinkLike, t: ProbeTarget, frm: F, d: F, travel: float, feed: float, what: str) -> F:
    # Only the probe-specific driver errors are translated; link loss etc. pass through.
    from drivers.grbl import ProbeError

    target = frm + d * travel
    try:
        step = link.probe((float(target[0]), float(target[1]), float(target[2])), feed, mode="G38.2")
        res = await probing(link, step, f"probe point {t.name}, {what} touch", travel, feed)
    except ProbeError as exc:
        text = str(exc)
        if exc.code == 4:
            raise ProbeCycleError(f"probe point {_where(t)}: the probe was already tripped at the {what} touch "
                                  f"({text}); clear the stylus and unlock ($X)") from None
        raise ProbeCycleError(f"probe point {_where(t)}: no contact within {travel:.3f} mm of travel on the {what} "
                              f"touch ({text}); check the workpiece position and the probe plan") from None
    if not res.contact:
        raise ProbeCycleError(f"probe point {_where(t)}: no contact within {travel:.3f} mm of travel on the {what} touch")
    return np.asarray(res.position[:3], dtype=float)


async def probe_point(link: CncLinkLike, t: ProbeTarget, s: ProbeSettings, log: ProbeLog | None = None) -> ProbedPoint:
    """Probe one point (fast, back off, `samples` slow touches; retry on spread). Ends retracted."""
    if not link.homed:
        raise ProbeCycleError(f"probe point {t.name}: the CNC is not homed; home it ($H) before probing")
    d = np.asarray(t.direction, dtype=float)
    d = d / np.linalg.norm(d)
    start = np.asarray(t.start, dtype=float)
    # The rotary axes do not move while probing: the newest background report is enough.
    st = link.latest_status or await link.status()
    table = (float(st.mpos[3]), float(st.mpos[4])) if len(st.mpos) >= 5 else (0.0, 0.0)
    await link.command(f"G90 G0 Z{fmt(max(t.safe_z, float(st.mpos[2])))}")
    await link.command(f"G0 X{fmt(start[0])} Y{fmt(start[1])}")
    await _rapid(link, start)
    spread = float("inf")
    samples = np.empty((0, 3))
    attempts = 0
    for attempts in range(1, int(s.retries) + 2):
        first = await _probe_once(link, t, start, d, float(s.travel_mm), float(s.fast_feed_mm_min), "fast")
        back = first - d * float(s.backoff_mm)
        got = []
        for k in range(int(s.samples)):
            await _rapid(link, back)
            # Slow touch: from the back-off point, up to twice the back-off past the fast contact.
            got.append(await _probe_once(link, t, back, d, 3.0 * float(s.backoff_mm), float(s.slow_feed_mm_min),
                                         f"slow #{k + 1}"))
        await _rapid(link, back)
        samples = np.array(got)
        along = samples @ d
        spread = float(along.max() - along.min())
        if log is not None:
            log.add(f"{t.name}: attempt {attempts}, {len(got)} samples, spread {spread * 1000:.1f} µm")
        if spread <= float(s.spread_tol_mm):
            break
    await _rapid(link, start)
    await link.command(f"G0 Z{fmt(max(t.safe_z, float(start[2])))}")
    if spread > float(s.spread_tol_mm):
        raise ProbeCycleError(f"probe point {_where(t)}: samples spread {spread * 1000:.1f} µm, above the "
                              f"tolerance {float(s.spread_tol_mm) * 1000:.1f} µm after {attempts} attempts; "
                              "clean the surface and the stylus, or raise probe.spread_tol_mm in cell.yaml")
    return ProbedPoint(name=t.name, position=samples.mean(axis=0), samples=samples, spread_mm=spread,
                       attempts=attempts, table_deg=table, direction=d)


async def probe_points(link: CncLinkLike, targets: Sequence[ProbeTarget], s: ProbeSettings, log: ProbeLog | None = None,
                       on_point: Callable[[ProbedPoint], None] | None = None) -> list[ProbedPoint]:
    """Probe a list (or grid) of points in order."""
    out = []
    for t in targets:
        p = await probe_point(link, t, s, log)
        out.append(p)
        if on_point is not None:
            on_point(p)
    return out
