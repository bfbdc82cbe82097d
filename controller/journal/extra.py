"""Per-bead figures the journal keeps as JSON in its `bead_extra` table (written by Journal.bead).

controller/runtime/bead_measure.py measures them: the bead's arc time (process s), the torch's
stand-stills with the arc on, and the 5th/95th percentiles of current, voltage and wire feed.
A new table (not new columns), so a journal written before them opens unchanged.
"""
from __future__ import annotations

import json
from typing import Any

BEAD_EXTRA = ("arc_s", "still_n", "still_s", "still_max_s", "lag_s", "i_p5", "i_p95", "u_p5", "u_p95", "wfs_p5", "wfs_p95",
               "slowed_n")


def read_extra(info: str) -> dict[str, Any]:
    """One row's figures; a damaged row gives none (the bead keeps its other figures)."""
    try:
        d = json.loads(info)
    except ValueError:
        return {}
    return d if isinstance(d, dict) else {}
