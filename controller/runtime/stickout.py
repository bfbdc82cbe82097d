"""Stick-out through the arc (docs/closed-loop.md): the CTWD of a bead from the power source's
measured current at the commanded wire feed, inverting the wire's melting-rate relation
(core/melting.py: `stick_out_at`, the material's calibrated α, β anchored to its synergic line).

Robust over the bead's steady part: the samples of the middle `steady_share` of the bead (the
arc start and the crater, where the pool is not yet / no longer on the bead's top, and a wall's
rounded ends are left out), then a trimmed mean of the current (a quarter of the samples off each
tail: a short arc flicker or a spatter spike does not move it). The current's ripple (the
material's `current_noise_pct`, 0.5 % 1σ: ±0.3 mm on one sample) averages out over the bead.
Pure: no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from core.material import Material
from core.melting import MeltingRelation, relation_for, sensitivity_a_per_mm, stick_out_at

__all__ = ["StickOut", "steady", "trimmed_mean", "StickOutEstimator"]


@dataclass(frozen=True)
class StickOut:
    stick_out_mm: float      # the estimate
    current_a: float         # the robust current it was read from
    n: int                   # samples used
    sigma_mm: float | None   # the estimate's standard error (from the samples' spread), None below 3


def steady(samples: Sequence[float], share: float) -> list[float]:
    """The middle `share` of the samples (at least one, when there is any)."""
    n = len(samples)
    if n <= 2:
        return list(samples)
    drop = int(n * (1.0 - share) / 2.0)
    mid = list(samples[drop:n - drop])
    return mid or list(samples[n // 2:n // 2 + 1])


def trimmed_mean(values: Sequence[float], cut: float = 0.25) -> float:
    """Mean of the values without `cut` of them off each tail (the median for one or two)."""
    v = sorted(values)
    if not v:
        raise ValueError("no samples")
    k = int(len(v) * cut)
    mid = v[k:len(v) - k] or v
    return sum(mid) / len(mid)


class StickOutEstimator:
    """The material's relation, inverted per bead."""

    def __init__(self, material: Material, steady_share: float = 0.6) -> None:
        self.material = material
        self.rel: MeltingRelation = relation_for(material)
        self.steady_share = steady_share

    @property
    def nominal_mm(self) -> float:
        return self.rel.stick_out_mm

    def sensitivity(self, wfs_m_min: float) -> float:
        """dI/dL (A/mm) at the nominal stick-out for this wire feed."""
        return sensitivity_a_per_mm(self.rel, self.material.ribeiro, wfs_m_min)

    def estimate(self, currents: Sequence[float], wfs_m_min: float) -> StickOut | None:
        """The bead's stick-out from its arc-stable current samples at the commanded wire feed."""
        mid = [float(i) for i in steady(currents, self.steady_share) if i > 0 and math.isfinite(i)]
        if not mid or wfs_m_min <= 0:
            return None
        i = trimmed_mean(mid)
        L = stick_out_at(self.rel, self.material.ribeiro, wfs_m_min, i)
        sigma = None
        if len(mid) >= 3:
            m = sum(mid) / len(mid)
            sd = math.sqrt(sum((x - m) ** 2 for x in mid) / (len(mid) - 1))
            sens = abs(self.sensitivity(wfs_m_min)) or 1.0
            sigma = sd / math.sqrt(len(mid)) / sens
        return StickOut(L, i, len(mid), sigma)
