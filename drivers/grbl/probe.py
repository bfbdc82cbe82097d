"""Probing for the grbl driver (link.py: `CncLink.probe`): `G38.x` toward a target,
the `[PRB:…]` result, and the recovery after a failed probe (unlock, retract, confirm Idle)."""
from __future__ import annotations

from typing import Protocol

from core.errors import InputError
from drivers.errors import DeviceError
from drivers.grbl.errors import ProbeError
from drivers.grbl.results import ProbeResult
from wire.grbl_protocol import AXES, GrblStatus, fmt, parse_probe

__all__ = ["Prober", "ProbeLink"]


class ProbeLink(Protocol):
    """What probing needs of the link (CncLink): public commands only."""

    url: str
    latest_status: GrblStatus | None

    async def command(self, line: str, timeout: float | None = None) -> list[str]: ...
    async def status(self, timeout: float | None = None) -> GrblStatus: ...
    async def wait_idle(self, timeout: float = 60.0) -> GrblStatus: ...


class Prober:
    """Probing moves on one link."""

    def __init__(self, link: ProbeLink) -> None:
        self.link = link

    async def _recover(self, start: GrblStatus) -> str:
        """After a failed probe: `$X`, retract Z to where the probe started (machine coordinates;
        never down: `start` may be the report from before the last rapid ended), and confirm Idle
        from a status report. Returns a note for the error."""
        try:
            await self.link.command("$X")
            z = max(start.mpos[2], (await self.link.status()).mpos[2])
            await self.link.command(f"G53 G0 Z{fmt(z)}")
            st = await self.link.wait_idle(30.0)
        except DeviceError as e:
            return f"; recovery failed ({e}): unlock ($X) and retract by hand"
        return f"; recovered: unlocked, Z retracted to {z:.3f} (machine), state {st.state}"

    async def run(self, target: dict[str, float] | tuple[float, float, float], feed_mm_min: float, *,
                    mode: str = "G38.2", unlock_on_fail: bool = True) -> ProbeResult:
        """Probe toward `target` (absolute, G90, in the active work coordinates; with grbl's
        default G54 offsets of zero these are machine coordinates) at `feed_mm_min`.

        Returns the trip position in machine coordinates ([PRB:…]) and `contact`. G38.2 without
        contact (ALARM:5) or with the probe already tripped (ALARM:4) raises ProbeError; by
        default the alarm lock is then cleared with `$X` (probe alarms do not lose position).
        G38.3 returns `contact=False` on a miss."""
        if mode not in ("G38.2", "G38.3", "G38.4", "G38.5"):
            raise InputError(f"cnc probe: mode {mode!r}; use G38.2 or G38.3")
        if not feed_mm_min > 0:
            raise InputError(f"cnc probe: feed {feed_mm_min} mm/min must be positive")
        if isinstance(target, dict):
            items = []
            for k, v in target.items():
                if k.lower() not in AXES:
                    raise InputError(f"cnc probe: unknown axis {k!r}; use x, y, z, a, b")
                items.append((k.upper(), float(v)))
        else:
            items = list(zip("XYZ", (float(v) for v in target)))
        words = " ".join(f"{k}{fmt(v)}" for k, v in items)
        line = f"{mode} G90 {words} F{feed_mm_min:g}"
        where = f" toward {words}"
        # only a failed probe's recovery reads it: the newest background report (≤ 5 Hz), not a
        # fresh one (waiting for the next poll cost up to 200 ms per touch, 4 touches per point)
        start = self.link.latest_status or await self.link.status()
        try:
            lines = await self.link.command(line)
        except ProbeError as exc:
            hint = ("; back off before probing again" if exc.code == 4
                    else "; check the travel, the part's position and the probe")
            if unlock_on_fail:
                hint += await self._recover(start)
            raise ProbeError(exc.code, line, self.link.url, where + hint) from None
        for text in reversed(lines):
            if text.startswith("[PRB:"):
                prb = parse_probe(text)
                return ProbeResult(prb.position, prb.success)
        raise DeviceError(f"cnc at {self.link.url}: {line!r} answered without a [PRB:…] report")
