"""The simulated world's process physics: bead geometry, stick-out and the melting rate (§6b).

`ProcessPhysics` belongs to the World (sims/world.py) when the simulators are served with a
material and sim.yaml's `process:` section (`sims.context.attach(ctx)`, called by every simulator's `serve`):

- one height map (sims/heightmap.py) per motion device, in its substrate frame: the robot's
  own frame (substrate z = 0), the CNC's workpiece frame (the workpiece mesh under it);
- each deposited segment pours a bead: width from Ribeiro's forward model at the segment's
  actual current and travel speed, metal = the wire fed (π·D²/4 · WFS / S) times
  `k = height_gain · (1 + height_temp_coeff · (T − 100 °C)⁺) · (1 + height_noise_pct/100 · N)`,
  N drawn once per bead (seeded), T the cell-I/O thermal model's part temperature; inside a
  `regions` box its own gain and temperature coefficient; the first `start_run_in_mm` of a bead
  lay a share of it (half at the start, linearly to all), and an open end loses `end_sag` of its
  last width's metal when the arc goes out (hidden disturbances along the path);
- the CTWD of the torch: the contact tip sits `stick_out_mm` above the tool point along the tool
  axis; CTWD = stick_out_mm + (tool z − (surface before this bead + the bead's rise)) / axis z;
- the melting-rate relation (core/melting.py) the power-source simulator follows at that CTWD.

Conventions and figures: docs/process-physics.md.
"""
from __future__ import annotations

import math
from typing import Callable, Generator

import numpy as np

from core.bead_model import ribeiro_forward, wire_area_mm2
from core.config import ProcessSim
from core.material import Material
from core.melting import MeltingRelation, current_at, relation_for, stick_out_factor
from sims.heightmap import HeightMap, Substrate
from sims.pour import Laid, finish

Vec3 = tuple[float, float, float]
REF_TEMP_C = 100.0
RUN_IN_START = 0.5      # the metal share at a bead's very start when `start_run_in_mm` > 0
MIN_AXIS_Z = 0.2


class ProcessPhysics:
    """Height maps, CTWD and the melting-rate truth of one simulated cell (not thread-safe: the World locks)."""

    def __init__(self, material: Material, cfg: ProcessSim | None = None, *, seed: int = 0) -> None:
        self.material = material
        self.cfg = cfg if cfg is not None else ProcessSim()
        self.melting: MeltingRelation = relation_for(material, self.cfg.stick_out_mm, self.cfg.resistive_share)
        self.maps: dict[str, HeightMap] = {}
        self._substrates: dict[str, Substrate] = {}
        self._rng = np.random.default_rng([int(seed), 27])
        self._temperature: Callable[[], float] | None = None
        self._torch: tuple[str, Vec3, Vec3, Vec3] | None = None    # device, tool point, axis, direction
        self._rise: dict[str, float] = {}
        self._noise = 1.0
        self._bead_mm = 0.0                       # path laid by the current bead (run-in)
        self._last_lay: tuple[str, tuple[float, float], float] | None = None   # device, direction, width

    # -- wiring --------------------------------------------------------------------------------
    def set_substrate(self, device: str, substrate: Substrate) -> None:
        """The substrate under a device's height map (before its first deposit)."""
        self._substrates[device] = substrate
        if device in self.maps:
            self.maps[device].substrate = substrate

    def set_temperature_source(self, fn: Callable[[], float]) -> None:
        """Where the part temperature comes from (the cell-I/O simulator's thermal model)."""
        self._temperature = fn

    def height_map(self, device: str) -> HeightMap:
        hm = self.maps.get(device)
        if hm is None:
            hm = self.maps[device] = HeightMap(self.cfg.cell_mm, self._substrates.get(device))
        return hm

    # -- beads ---------------------------------------------------------------------------------
    def new_bead(self) -> None:
        """The arc became stable: a new bead (its noise drawn now, the same for all its segments)."""
        pct = self.cfg.height_noise_pct
        self._noise = 1.0 + pct / 100.0 * float(self._rng.standard_normal()) if pct else 1.0
        self._bead_mm, self._last_lay = 0.0, None
        for hm in self.maps.values():
            hm.new_bead()

    def part_temperature_c(self) -> float:
        return float(self._temperature()) if self._temperature is not None else 20.0

    def height_factor(self, xy: tuple[float, float] | None = None, temp_c: float | None = None) -> float:
        """k: the true metal (height at the model's width) over the model's, at a point of the
        substrate frame (a region's own gains there) and a part temperature (else now's)."""
        c = self.cfg
        gain, coeff = c.height_gain, c.height_temp_coeff
        if xy is not None:
            for r in c.regions:           # the last region listed wins
                if r.contains(xy[0], xy[1]):
                    gain, coeff = r.height_gain, r.height_temp_coeff
        t = self.part_temperature_c() if temp_c is None else temp_c
        hot = max(t - REF_TEMP_C, 0.0)
        return max(gain * (1.0 + coeff * hot) * self._noise, 0.05)

    def lay(self, device: str, q0: Vec3, q1: Vec3, duration_s: float, current_a: float,
            wfs_m_min: float, temp_c: float | None = None) -> Laid | None:
        """The bead of one deposited segment (substrate frame); None when it lays no metal.
        `temp_c`: the part temperature when the segment was deposited (else now's)."""
        return finish(self.lay_steps(device, q0, q1, duration_s, current_a, wfs_m_min, temp_c))

    def lay_steps(self, device: str, q0: Vec3, q1: Vec3, duration_s: float, current_a: float,
                  wfs_m_min: float, temp_c: float | None = None) -> Generator[None, None, Laid | None]:
        """`lay`, resumable (HeightMap.lay_steps: a yield every 10 mm of bead). Each 1 mm chunk
        gets the factor of where it lies: a region's gains, the run-in's share."""
        length = math.dist(q0[:2], q1[:2])
        if length < 1e-9 or duration_s <= 0 or current_a <= 0 or wfs_m_min <= 0:
            return None
        speed = length / duration_s * 60.0
        width, _ = ribeiro_forward(self.material.ribeiro, current_a, speed)
        wire = wire_area_mm2(self.material.wire_diameter_mm, wfs_m_min, speed)
        hm = self.height_map(device)
        if hm.bead == 0:
            hm.new_bead()
        s0 = self._bead_mm

        def scale(x: float, y: float, s: float) -> float:
            return self.height_factor((x, y), temp_c) * self.run_in_share(s0 + s)

        laid = yield from hm.lay_steps((q0[0], q0[1]), (q1[0], q1[1]), width, wire, scale=scale)
        self._bead_mm = s0 + length
        self._last_lay = (device, (q1[0] - q0[0], q1[1] - q0[1]), width)
        if laid.rise_mm is not None:
            self._rise[device] = laid.rise_mm
        return laid

    def run_in_share(self, s_mm: float) -> float:
        """The metal share laid `s_mm` after a bead's start: RUN_IN_START at the start, linearly
        to 1 at `start_run_in_mm`."""
        n = self.cfg.start_run_in_mm
        if n <= 0.0 or s_mm >= n:
            return 1.0
        return RUN_IN_START + (1.0 - RUN_IN_START) * max(s_mm, 0.0) / n

    def end_bead(self) -> float:
        """The arc went out: the bead's end poured (its round end), an open end sags (`end_sag`);
        the mm³ that ran off."""
        last, self._last_lay = self._last_lay, None
        for hm in self.maps.values():
            hm.end_bead()
        if last is None or self.cfg.end_sag <= 0.0:
            return 0.0
        device, direction, width = last
        return self.height_map(device).sag_end(direction, width, self.cfg.end_sag)

    def rise_mm(self, device: str) -> float:
        """The latest settled rise of a device's bead on its centre line (0 before any)."""
        return self._rise.get(device, 0.0)

    # -- the torch -----------------------------------------------------------------------------
    def torch_at(self, device: str, tool: Vec3, axis: Vec3, direction: Vec3) -> None:
        """The torch's tool point and axis (substrate frame) and its direction of travel."""
        self._torch = (device, tool, axis, direction)

    def ctwd_mm(self) -> float | None:
        """CTWD of the torch now (mm), or None before any torch motion."""
        if self._torch is None:
            return None
        device, q, axis, _ = self._torch
        hm = self.height_map(device)
        ground = hm.surface(q[0], q[1], before_bead=True)
        top = ground + self._rise.get(device, 0.0)
        az = max(abs(axis[2]), MIN_AXIS_Z)
        return self.cfg.stick_out_mm + (q[2] - top) / az

    def current_a(self, wfs_m_min: float, stick_out_mm: float, synergic_a: float | None = None) -> float:
        """The source's current at a wire feed and stick-out (the melting-rate truth).

        `synergic_a`: the source's own synergic current at that feed (scaled, so the nominal
        stick-out gives it bit for bit); else the material's line.
        """
        if synergic_a is None:
            return current_at(self.melting, self.material.ribeiro, wfs_m_min, stick_out_mm)
        return synergic_a * stick_out_factor(self.melting, wfs_m_min, stick_out_mm)
