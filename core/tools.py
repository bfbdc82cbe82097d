"""The cell's tools (cell.yaml `tools:`) and its finish machining settings (`machining:`).

The hybrid cell carries the deposition head (whose touch probe is the machine's length
reference, tool length 0) and one or more cutters (docs/machining.md). Every cutter names its
shape (`flat` or `ball`), its diameter, flute length, spindle limits, the depth of cut and
stepover it may take, and its length offset: how far its tip reaches below the head's
reference point (the controller applies it as `G43.1 Z…`; on stock grbl 1.1h it is measured
again on the tool setter after every change).
"""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class DepositionHead(_Frozen):
    """The deposition head (torch or laser) with its touch probe: tool `number`, length 0."""

    number: int = Field(default=0, ge=0, le=99)
    length_offset_mm: float = Field(default=0.0, ge=-200.0, le=200.0)


class Cutter(_Frozen):
    """A milling cutter in the spindle."""

    number: int = Field(ge=0, le=99)
    type: Literal["flat", "ball"]
    diameter_mm: float = Field(gt=0.0, le=50.0)
    flute_length_mm: float = Field(gt=0.0, le=200.0)
    max_rpm: float = Field(gt=0.0, le=100000.0)
    rpm: float | None = Field(default=None, gt=0.0, description="spindle speed used (null: 80 % of max_rpm)")
    feed_mm_min: float = Field(default=600.0, gt=0.0, le=20000.0)
    max_depth_of_cut_mm: float = Field(gt=0.0, le=50.0)
    max_stepover_mm: float = Field(gt=0.0, le=50.0)
    length_offset_mm: float = Field(default=0.0, ge=-200.0, le=200.0)

    @property
    def radius_mm(self) -> float:
        return self.diameter_mm / 2.0

    @property
    def spindle_rpm(self) -> float:
        return self.rpm if self.rpm is not None else 0.8 * self.max_rpm

    @model_validator(mode="after")
    def _limits(self) -> "Cutter":
        if self.rpm is not None and self.rpm > self.max_rpm:
            raise ValueError(f"rpm {self.rpm:g} is above max_rpm {self.max_rpm:g}")
        if self.max_depth_of_cut_mm > self.flute_length_mm:
            raise ValueError(f"max_depth_of_cut_mm {self.max_depth_of_cut_mm:g} is deeper than the flutes "
                             f"({self.flute_length_mm:g} mm)")
        if self.max_stepover_mm > self.diameter_mm:
            raise ValueError(f"max_stepover_mm {self.max_stepover_mm:g} is wider than the cutter "
                             f"({self.diameter_mm:g} mm)")
        return self


def _default_cutters() -> dict[str, Cutter]:
    return {"ball6": Cutter(number=1, type="ball", diameter_mm=6.0, flute_length_mm=12.0, max_rpm=18000.0,
                            rpm=12000.0, feed_mm_min=900.0, max_depth_of_cut_mm=1.0, max_stepover_mm=2.0)}


class Tools(_Frozen):
    """`tools:` the deposition head, the cutters by name, and the tool setter."""

    deposition: DepositionHead = DepositionHead()
    cutters: dict[str, Cutter] = Field(default_factory=_default_cutters)
    # the tool setter's top (machine frame): grbl 1.1h measures a cutter's length there after a change
    setter_mm: tuple[float, float, float] = (-150.0, -150.0, 0.0)

    @model_validator(mode="after")
    def _numbers(self) -> "Tools":
        if not self.cutters:
            raise ValueError("cutters: at least one cutter is needed to machine a deposit")
        seen = {self.deposition.number: "deposition"}
        for name, c in self.cutters.items():
            if c.number in seen:
                raise ValueError(f"cutters.{name}: tool number {c.number} is also {seen[c.number]}'s; "
                                 "give every tool its own number")
            seen[c.number] = name
        return self

    def cutter(self, name: str | None) -> tuple[str, Cutter]:
        """The cutter called `name` (None: the first); KeyError naming the known ones."""
        if name is None:
            first = next(iter(self.cutters))
            return first, self.cutters[first]
        if name not in self.cutters:
            raise KeyError(f"no cutter {name!r} in cell.yaml tools.cutters (known: {', '.join(self.cutters)})")
        return name, self.cutters[name]


class Machining(_Frozen):
    """`machining:` how a deposit is brought to the drawing (docs/contract.md §4, docs/machining.md)."""

    cutter: str | None = None             # tools.cutters name; null: the first
    min_stock_mm: float = Field(default=0.2, ge=0.0, le=10.0, description="deposit above CAD everywhere before machining")
    finish_stock_mm: float = Field(default=0.2, ge=0.0, le=5.0, description="left by roughing for the finishing pass")
    scallop_mm: float = Field(default=0.01, gt=0.0, le=0.5)
    margin_mm: float = Field(default=2.0, ge=0.0, le=50.0, description="machined beyond the repair region")
    redeposit_rounds: int = Field(default=1, ge=0, le=5, description="deposits again where short, at most this often")
    probe_points: int = Field(default=16, ge=3, le=200, description="stock-probe and verify touches over the region")
    ripple_mm: float = Field(default=0.5, ge=0.0, le=5.0, description="the deposit above its probed touches, "
                             "at most (roughing starts this much higher)")
    verify_tolerance_mm: float = Field(default=0.05, gt=0.0, le=5.0, description="machined verify: |z - CAD| beyond is a defect")
