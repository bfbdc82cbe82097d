"""cell.yaml's `process_control:` (docs/closed-loop.md): the layer loop and the path loop's settings."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ProcessControl(_Frozen):
    """Closed-loop layer height (docs/contract.md §6b, docs/closed-loop.md); `open` keeps the plan's z."""

    mode: Literal["open", "layer", "path"] = "open"   # path: the layer loop plus per-segment speeds along the path
    ctwd_window_mm: tuple[float, float] = (12.0, 18.0)   # the stick-out (CTWD) allowed: outside pauses before the next layer
    probe_every_layers: int = Field(default=1, ge=1, le=1000)   # CNC: probe the top every n layers
    probe_points: int = Field(default=4, ge=1, le=50)           # CNC: points per probed layer
    max_z_correction_mm: float = Field(default=5.0, gt=0.0, le=100.0)  # beyond: pause with a message
    speed_trim_pct: float = Field(default=25.0, ge=0.0, le=60.0)  # travel speed within ± this of the plan
    layer_change: Literal["add_drop", "none"] = "add_drop"      # add / drop top layers when the trim saturates
    max_layer_change_pct: float = Field(default=50.0, ge=0.0, le=200.0)  # at most this share of layers added / dropped
    gain_window_layers: int = Field(default=6, ge=2, le=100)    # measured tops the gain is fitted over
    steady_share: float = Field(default=0.6, gt=0.0, le=1.0)    # middle share of a bead's samples estimated
    # the trim aims at the plan's top this many layers on (null: path mode 2, layer mode the build's end)
    catch_up_layers: int | None = Field(default=None, ge=1, le=1000)
    # the path loop (mode path, docs/closed-loop.md "Along the path")
    probe_spacing_mm: float = Field(default=10.0, gt=0.0, le=1000.0)  # CNC: probe points along every pass
    path_bin_mm: float | None = Field(default=None, gt=0.0, le=100.0)  # robot: samples binned this long (null: the bead width)
    path_filter_mm: float | None = Field(default=None, gt=0.0, le=200.0)  # filter length along the path (null: 1.5 bead widths; at least one)
    path_kp: float = Field(default=0.4, ge=0.0, le=2.0)         # learning on the change of the error since the last layer
    path_ki: float = Field(default=0.2, ge=0.0, le=2.0)        # learning on the error
    path_max_error_mm: float = Field(default=1.0, gt=0.0, le=50.0)  # off the layer's mean by more, at the bound: pause
    path_wfs_trim_pct: float = Field(default=0.0, ge=0.0, le=40.0)  # wire feed within ± this, the bead's width kept (0: speed only)
    path_edges: bool = False   # robot: split the passes at a hidden region's edge found in the raw stick-out (docs/closed-loop.md "Region edges")
    # the path loop's speed factor per segment within [lo, hi] × the planned speed (null: ± speed_trim_pct)
    path_speed_range: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _window(self) -> "ProcessControl":
        lo, hi = self.ctwd_window_mm
        if not 0.0 < lo < hi:
            raise ValueError(f"ctwd_window_mm: needs 0 < lo < hi (got [{lo}, {hi}])")
        if self.path_speed_range is not None and not 0.1 <= self.path_speed_range[0] <= 1.0 <= self.path_speed_range[1] <= 3.0:
            raise ValueError(f"path_speed_range: needs 0.1 <= lo <= 1 <= hi <= 3 (got {list(self.path_speed_range)})")
        return self
