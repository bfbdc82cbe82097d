"""Material and process coefficients (the paper's CONST.INS), as a frozen, validated object."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Frozen(BaseModel):
    # allow_inf_nan=False: `k1: .inf` is an error naming the key (issue 14)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class RibeiroCoefficients(_Frozen):
    """Power-law coefficients: w = K1·I^K2·S^K3, h = K4·I^K5·S^K6 (I in A, S in mm/min, mm)."""

    ratio: float = Field(gt=0.0, lt=2.0, description="default height/width ratio")
    k1: float = Field(gt=0.0)
    k2: float = Field(gt=-10.0, lt=10.0)
    k3: float = Field(gt=-10.0, lt=10.0)
    k4: float = Field(gt=0.0)
    k5: float = Field(gt=-10.0, lt=10.0)
    k6: float = Field(gt=-10.0, lt=10.0)
    i_min_a: float = Field(gt=0.0, le=2000.0)
    i_max_a: float = Field(gt=0.0, le=2000.0)
    wfs_min_m_min: float = Field(gt=0.0, le=50.0)
    wfs_max_m_min: float = Field(gt=0.0, le=50.0)

    @model_validator(mode="after")
    def _ordered(self) -> "RibeiroCoefficients":
        if self.i_min_a >= self.i_max_a:
            raise ValueError("i_min_a must be below i_max_a")
        if self.wfs_min_m_min >= self.wfs_max_m_min:
            raise ValueError("wfs_min_m_min must be below wfs_max_m_min")
        if abs(self.k2 * self.k6 - self.k3 * self.k5) < 1e-9:
            raise ValueError("k2*k6 - k3*k5 is zero: the model cannot be inverted")
        return self


class BeadSettings(_Frozen):
    profile: Literal["parabola", "cosine", "arc"] = "parabola"
    overlap_model: Literal["tangent", "flat_top"] = "tangent"
    # Ding 2015: centres closer than this share of the width over-build the overlap (unstable).
    min_step_over_ratio: float = Field(default=2.0 / 3.0, gt=0.3, lt=1.0)


class InterpassSettings(_Frozen):
    max_temperature_c: float = Field(gt=0.0, le=1500.0)
    dwell_s: float = Field(ge=0.0, le=3600.0)


class ProcessTolerance(_Frozen):
    """How far the measured process may stray from the plan while a bead is deposited (issue 13).

    Current and wire feed: relative to the pass's planned values; voltage: an absolute window
    (the plan carries no voltage, the synergic source chooses it). A bead outside any of them,
    or whose arc was not stable all along, is a defect.
    """

    current_pct: float = Field(default=10.0, gt=0.0, le=100.0)
    wfs_pct: float = Field(default=10.0, gt=0.0, le=100.0)
    # the robot's measured travel speed: beads outside it are flagged in the record, not defects
    speed_pct: float = Field(default=10.0, gt=0.0, le=100.0)
    voltage_min_v: float = Field(default=10.0, ge=0.0, le=100.0)
    voltage_max_v: float = Field(default=40.0, gt=0.0, le=200.0)

    @model_validator(mode="after")
    def _window(self) -> "ProcessTolerance":
        if self.voltage_min_v >= self.voltage_max_v:
            raise ValueError("voltage_min_v must be below voltage_max_v")
        return self


class MeltingSettings(_Frozen):
    """Wire melting rate `WFS = α·I + β·L·I²` (core/melting.py, docs/process-physics.md).

    Without `alpha`/`beta`, they are calibrated from the synergic line at `stick_out_mm`, with the
    resistive term `resistive_share` of the melting at `reference_current_a` (default: the middle
    of [Imin, Imax]); `cell process stickout-fit` refits them from a stick-out sweep.
    """

    stick_out_mm: float = Field(default=15.0, gt=0.0, le=60.0, description="nominal CTWD of the synergic line")
    resistive_share: float = Field(default=0.4, ge=0.05, le=0.8)
    reference_current_a: float | None = Field(default=None, gt=0.0, le=2000.0)
    alpha: float | None = Field(default=None, gt=0.0, description="(m/min)/A")
    beta: float | None = Field(default=None, gt=0.0, description="(m/min)/(A²·mm)")
    # relative 1σ ripple of the measured current (the power source's and its simulator's)
    current_noise_pct: float = Field(default=0.5, ge=0.0, le=20.0)

    @model_validator(mode="after")
    def _both(self) -> "MeltingSettings":
        if (self.alpha is None) != (self.beta is None):
            raise ValueError("give both alpha and beta (from `cell process stickout-fit`) or neither")
        return self


class Material(_Frozen):
    name: str = Field(min_length=1)
    process: Literal["gmaw", "cmt", "laser"] = "gmaw"
    wire_diameter_mm: float = Field(gt=0.2, le=5.0)
    wire_density_g_cm3: float = Field(gt=0.5, le=25.0)
    gas: str = Field(min_length=1)
    arc_efficiency: float = Field(gt=0.0, le=1.0, description="η for heat input η·U·I")
    ribeiro: RibeiroCoefficients
    bead: BeadSettings = BeadSettings()
    interpass: InterpassSettings
    min_bead_length_mm: float | None = Field(default=None, gt=0.0, le=1000.0,
                                             description="shortest pass; default 2 bead widths")
    max_overhang_deg: float = Field(default=30.0, ge=0.0, lt=90.0,
                                    description="wall lean from vertical a 3-axis path may build")
    machining_allowance_mm: float | None = Field(default=None, ge=0.0, le=100.0,
                                                 description="near-net stock per face; default 0 (net shape)")
    tolerance: ProcessTolerance = ProcessTolerance()
    # exclude=True: not in `model_dump`, so a job (which carries the material's dump) is byte for
    # byte what it was before this section existed; the controller reads it from the material file
    melting: MeltingSettings = Field(default=MeltingSettings(), exclude=True)
