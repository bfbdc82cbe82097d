"""Material and process coefficients (the paper's CONST.INS), as a frozen, validated object."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


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


class InterpassSettings(_Frozen):
    max_temperature_c: float = Field(gt=0.0, le=1500.0)
    dwell_s: float = Field(ge=0.0, le=3600.0)


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
