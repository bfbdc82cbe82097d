"""The plan's verdict: what cannot be planned fails the plan naming the layers (or, when the user
allows it, becomes a warning in the summary). Nothing is dropped silently (docs/contract.md §3.6)."""
from __future__ import annotations

from core.errors import MeshError
import re
from typing import TYPE_CHECKING, Any

import shapely

from planner.layer import ALLOWANCE_HINT, LayerCtx, LayerPlan
from planner.options import PlanOptions
from planner.overhang import check_overhang
from planner.summary import LayerQuality, gap_message

if TYPE_CHECKING:  # annotations only: `cell plan` passes a remembered material (core.config_cache) and
    # never imports pydantic
    from core.material import Material

MAX_LISTED = 6
# near-net: the share of the deposit's footprint outside the grown region a plan may have (issue 40); a plan
# over it whose features were built standing out of the grown region refuses those features
OUTSIDE_MAX = 0.015


class Verdict:
    """Collects underfill, coverage, stub, overhang and mass-balance findings layer by layer."""

    def __init__(self, options: PlanOptions, material: Material, ctx: LayerCtx) -> None:
        self.opt, self.mat, self.ctx = options, material, ctx
        self.underfill: list[str] = []
        self.coverage: list[str] = []
        self.stubs: list[str] = []
        self.standout: list[str] = []  # near-net: features built standing out of the grown region
        self.unfilled: list[str] = []  # unfilled areas over one bead's footprint, named
        self.overhang: list[str] = []
        self.overhang_layers: list[int] = []
        self.regions = 0
        self.worst_balance = 0.0
        self.limits: list[tuple[str, bool]] = []  # beads outside the cell's limits (message, fatal anyway)
        self.wfs_adjusted = 0  # passes whose wire feed was moved to keep the speed in the cell's range
        self.worst_layer_balance = 0.0  # |metal laid - section x h| / (section x h), worst layer
        self.close = (0.0, 0)  # Ding: worst share of bead length with a too-close neighbour, its layer

    def layer(self, index: int, lp: LayerPlan, q: LayerQuality, below: shapely.Geometry | None,
              height: float) -> None:
        """Findings of one planned layer (`lp`: LayerPlan, `q`: LayerQuality, `below`: region or None)."""
        self.regions += not lp.region.is_empty
        self.underfill += lp.issues
        self.stubs += lp.stubs
        self.standout += lp.standout
        gaps = [gap_message(index, g) for g in q.gaps]
        self.unfilled += gaps
        if q.area_mm2 > 0 and q.coverage < self.opt.min_coverage:
            where = "".join("; " + gap_message(index, g).split(": ", 1)[1] for g in q.largest)
            self.coverage.append(f"layer {index}: {100 * q.coverage:.1f} % covered "
                                 f"(< {100 * self.opt.min_coverage:.0f} %){where}")
        oh = check_overhang(below, lp.region, height, self.ctx.width, self.mat.max_overhang_deg)
        if oh.where is not None:
            self.overhang_layers.append(index)
            self.overhang.append(f"layer {index}: steps out {oh.step_out_mm:.2f} mm at ({oh.where[0]:.1f}, "
                                 f"{oh.where[1]:.1f}), more than {oh.limit_mm:.2f} mm, {oh.unsupported_mm2:.0f} mm2 "
                                 f"unsupported")

    def ding(self, index: int, share: float) -> None:
        if share > self.close[0]:
            self.close = (share, index)

    def balance(self, err: float) -> None:
        self.worst_balance = max(self.worst_balance, err)

    def layer_balance(self, err: float) -> None:
        self.worst_layer_balance = max(self.worst_layer_balance, err)

    def finish(self, name: str, qualities: list[LayerQuality]) -> dict[str, Any]:
        """Summary fields; raises MeshError for what the options do not allow."""
        if self.regions == 0:
            raise MeshError(f"{name}: no layer has a closed region (the mesh is not a solid: a triangle soup "
                            f"or open surfaces); close the mesh and plan again")
        fatal: list[str] = []
        self.underfill += self._stood_out(qualities)
        fix = _allowance_fixes(self.underfill)
        if not self.opt.allow_underfill:
            fatal += _listed("feature(s) no legal bead fills", self.underfill, "--allow-underfill")
            if fix:
                fatal.append(f"--machining-allowance {max(fix.values()):.2f} would make {len(fix)} of the "
                             f"{len(self.underfill)} buildable")
            fatal += _listed("layer(s) below --min-coverage", self.coverage, "--allow-underfill")
        if not self.opt.allow_overhang and self.opt.five_axis is None:  # 5-axis: five_axis.apply
            fatal += _listed("layer(s) beyond the overhang rule (Kerschbaumer: step out <= dz*tan "
                             f"{self.mat.max_overhang_deg:g} deg and <= w/2)", self.overhang,
                             "--allow-overhang (or a 5-axis plan)")
        hard = [m for m, h in self.limits if h or not self.opt.allow_outside]
        fatal += _listed("bead(s) outside the cell's limits (cell.yaml limits, the material's envelope)", hard,
                         "--allow-outside, inside the power source's range,")
        if fatal:
            raise MeshError(f"{name}: " + "; ".join(fatal))
        worst = min(range(len(qualities)), key=lambda i: qualities[i].coverage) if qualities else 0
        return {
            "coverage_min_layer": worst,
            "mass_balance_max_error": round(self.worst_balance, 5),
            "mass_balance_layer_max": round(self.worst_layer_balance, 5),
            "close_neighbour_max": round(self.close[0], 4),  # below min_step_over_ratio x width
            "close_neighbour_layer": self.close[1],
            "overhang_layers": self.overhang_layers,
            "underfill_features": len(self.underfill),
            "stubs_dropped": len(self.stubs),
            "stubs": self.stubs[:50],
            "allowance_would_fix": [{"feature": m, "allowance_mm": a} for m, a in list(fix.items())[:50]],
            "unfilled_features": len(self.unfilled),
            "unfilled": self.unfilled[:50],
            "limits": {"max_speed_mm_min": self.opt.cell_limits.max_speed_mm_min,
                       "min_speed_mm_min": self.opt.cell_limits.min_speed_mm_min,
                       "wfs_adjusted_passes": self.wfs_adjusted,
                       "outside_passes": len(self.limits)},
            "warnings": (self.underfill + self.coverage + self.overhang + self.stubs + self.unfilled
                         + [m for m, _ in self.limits])[:50],
        }


    def _stood_out(self, qualities: list[LayerQuality]) -> list[str]:
        """Near-net: the features built standing out of the grown region, as features no legal bead
        fills, when the plan's footprint stands out of its grown region over OUTSIDE_MAX (a plan within
        it keeps them: the stock there is at most twice the allowance)."""
        fp = sum(q.footprint_mm2 for q in qualities)
        share = sum(q.overfill_mm2 for q in qualities) / fp if fp > 0 else 0.0
        if not self.standout or share <= OUTSIDE_MAX:
            return []
        return [f"{m} (the deposit would stand {100 * share:.1f} % out of its grown region, over "
                f"{100 * OUTSIDE_MAX:.1f} %)" for m in self.standout]


def _listed(what: str, items: list[str], flag: str) -> list[str]:
    if not items:
        return []
    more = f"; and {len(items) - MAX_LISTED} more" if len(items) > MAX_LISTED else ""
    return [f"{len(items)} {what}: " + "; ".join(items[:MAX_LISTED]) + more + f" ({flag} to plan anyway)"]


def _allowance_fixes(messages: list[str]) -> dict[str, float]:
    """Refused features a machining allowance would make buildable: {message: allowance mm}."""
    out: dict[str, float] = {}
    for m in messages:
        found = re.search(ALLOWANCE_HINT + r" ([0-9.]+) mm", m)
        if found:
            out[m] = float(found.group(1))
    return out
