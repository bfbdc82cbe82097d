"""Lumped thermal model of the part: one heat capacity, Newton cooling toward ambient.

    C·dT/dt = P(t) − C·(T − T_amb)/τ

with P = η·U·I while the arc burns (from the World). Integrated exactly over each step with P
held constant, so the result does not depend on the step size. Times are simulated seconds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class LumpedThermal:
    ambient_c: float = 20.0
    heat_capacity_j_k: float = 2000.0
    tau_s: float = 120.0
    temperature_c: float = math.nan   # the part now; NaN (the default): starts at ambient

    def __post_init__(self) -> None:
        if self.heat_capacity_j_k <= 0 or self.tau_s <= 0:
            raise ValueError("heat capacity and cooling time constant must be positive")
        if math.isnan(self.temperature_c):
            self.temperature_c = self.ambient_c

    def steady_c(self, power_w: float) -> float:
        """The temperature the part tends to under a constant heat input."""
        return self.ambient_c + power_w * self.tau_s / self.heat_capacity_j_k

    def step(self, power_w: float, dt_s: float) -> float:
        """Advance by `dt_s` simulated seconds under `power_w` watts; the new temperature."""
        if dt_s > 0:
            t_inf = self.steady_c(power_w)
            self.temperature_c = t_inf + (self.temperature_c - t_inf) * math.exp(-dt_s / self.tau_s)
        return self.temperature_c

    def time_to_cool(self, target_c: float) -> float:
        """Simulated seconds until the part cools (no heat input) to `target_c` (inf if never)."""
        if self.temperature_c <= target_c:
            return 0.0
        if target_c <= self.ambient_c:
            return math.inf
        return self.tau_s * math.log((self.temperature_c - self.ambient_c) / (target_c - self.ambient_c))
