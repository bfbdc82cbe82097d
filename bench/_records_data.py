"""Records shaped like report.json (controller/report/summary.py), made up for the record store's
tests and benches: many builds and beads without running a cell."""
from __future__ import annotations

import datetime as dt
import random
import uuid
from typing import Any

MATERIALS = ("inconel718-1.0mm", "er70s6-1.2mm")


def fake_record(i: int, *, beads: int = 8, lot: str | None = None, cell: str = "cell-01",
                material: str | None = None, defect_every: int = 0, started: dt.datetime | None = None,
                seed: int | None = None) -> dict[str, Any]:
    """Build `i`'s record: `beads` beads over layers of 4, a defect on every `defect_every`-th bead."""
    rnd = random.Random(i if seed is None else seed)
    t0 = started or dt.datetime(2026, 11, 1, tzinfo=dt.timezone.utc) + dt.timedelta(minutes=7 * i)
    rows = []
    for k in range(beads):
        bad = defect_every > 0 and k % defect_every == defect_every - 1
        cur = 120.0 + rnd.uniform(-3, 3) + (20.0 if bad else 0.0)
        rows.append({"layer": k // 4, "pass": k % 4, "role": "perimeter", "status": "defect" if bad else "done",
                     "runs": "1", "arc_time_s": round(rnd.uniform(2, 4), 3), "motion_time_s": 3.0, "still_time_s": 0.0,
                     "still_count": 0, "still_max_s": 0.0, "length_planned_mm": 40.0, "length_measured_mm": 40.0,
                     "current_planned_a": 120.0, "current_mean_a": round(cur, 2), "current_p5_a": 110.0,
                     "current_p95_a": 130.0, "current_min_a": 100.0, "current_max_a": 150.0,
                     "voltage_window_min_v": 10.0, "voltage_window_max_v": 30.0, "voltage_mean_v": 19.5,
                     "voltage_p5_v": 19.0, "voltage_p95_v": 20.0, "voltage_min_v": 18.0, "voltage_max_v": 21.0,
                     "wfs_planned_m_min": 5.5, "wfs_mean_m_min": 5.5, "wfs_p5_m_min": 5.4, "wfs_p95_m_min": 5.6,
                     "wfs_min_m_min": 5.3, "wfs_max_m_min": 5.7, "speed_planned_mm_min": 600.0,
                     "speed_measured_mm_min": 600.0, "starved_count": 0, "heat_input_j_mm": round(cur * 19.5 * 0.8 / 10, 3),
                     "defects_count": 1 if bad else 0, "defect_reasons": "current outside ±10 %" if bad else ""})
    layers = [{"layer": n, "start": (t0 + dt.timedelta(seconds=60 * n)).isoformat(), "interpass_temperature_c": 80.0,
               "interpass_limit_c": 150.0, "wait_s": 30.0 if n else None} for n in range((beads + 3) // 4)]
    return {"build_id": str(uuid.UUID(int=rnd.getrandbits(128), version=4)), "cell": cell,
            "job": {"name": f"part-{i % 17}", "hash": f"{i:064x}", "platform": "robot"},
            "state": "complete", "started": t0.isoformat(), "ended": (t0 + dt.timedelta(minutes=5)).isoformat(),
            "material": material or MATERIALS[i % 2], "wire": {"alloy": "x", "diameter_mm": 1.0, "lot": lot},
            "wire_lot": lot if lot is not None else f"LOT-{i % 50:03d}", "gas": "Ar", "operator": "A. Welder",
            "software_version": "0.1.0", "layers_total": len(layers), "passes_total": beads, "layers_done": len(layers),
            "passes_done": beads, "arc_starts": beads, "runs": 1, "arc_time_s": round(sum(b["arc_time_s"] for b in rows), 3),
            "deposit_length_mm": 40.0 * beads, "layers": layers, "beads": rows,
            "alarms": [], "bead_defects": sum(b["defects_count"] for b in rows), "traceability": []}
