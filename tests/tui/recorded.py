"""A recorded view of a build for the TUI's snapshot and guard tests."""
from __future__ import annotations

import math

from controller.runtime.events import Alarm, LinkStat, Snapshot
from controller.tui.session import LogRow, PlanStatus, Sample, View, job_info
from planner.job import load_job

T0 = 1_767_225_600.0   # 2026-01-01 00:00:00 UTC: every time on screen derives from it


def _loop(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0, 1.0], [x1, y0, 1.0], [x1, y1, 1.0], [x0, y1, 1.0], [x0, y0, 1.0]]


def recorded_job() -> dict:
    """A small cell-job/1: three layers of a 60 × 40 mm block with a slot, 2 perimeters + zigzag infill."""
    layers = []
    for li in range(3):
        z = 1.2 * (li + 1)
        passes = []
        for k, inset in enumerate((1.5, 4.5)):
            pts = [[x, y, z] for x, y, _ in _loop(inset, inset, 60 - inset, 40 - inset)]
            passes.append({"role": "perimeter", "width_mm": 3.0, "current_a": 120.0 + 2 * k, "speed_mm_min": 400.0,
                           "wfs_m_min": 5.5, "points": pts})
        zig = []
        for i, y in enumerate(range(8, 33, 3)):
            xs = (7.5, 52.5) if i % 2 == 0 else (52.5, 7.5)
            zig += [[xs[0], float(y), z], [xs[1], float(y), z]]
        passes.append({"role": "infill", "width_mm": 3.0, "current_a": 126.0, "speed_mm_min": 420.0,
                       "wfs_m_min": 5.8, "points": zig})
        passes.append({"role": "gap", "width_mm": 2.2, "current_a": 104.0, "speed_mm_min": 520.0,
                       "wfs_m_min": 4.6, "points": [[30.0, 5.0, z], [30.0, 7.0, z]]})
        layers.append({"index": li, "z_mm": z, "height_mm": 1.2, "passes": passes})
    return {"schema": "cell-job/1", "source": {"file": "block-slot.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 3.0, "height_mm": 1.2, "step_over_mm": 2.21, "model": "parabola/tangent"},
            "layers": layers,
            "summary": {"layers": 3, "passes": 12, "arc_starts": 12, "deposit_length_mm": 2411.6,
                        "volume_mm3": 7234.8, "coverage": 0.9871, "est_time_s": 512.0}}


def recorded_view(**snap_changes: object) -> View:
    """The cell in the middle of layer 2, recorded: fixed values everywhere."""
    links = (LinkStat("cnc", "socket://127.0.0.1:47602", True, 1520, 1498, 0, 96),
             LinkStat("power_source", "tcp://127.0.0.1:47603", True, 40210, 40210, 2, None),
             LinkStat("cellio", "tcp://127.0.0.1:47604", True, 40190, 40190, 0, None))
    alarms = (Alarm(T0 + 95.0, "warning", "interpass: part at 162 °C, limit 150 °C", layer=1, pass_=0),)
    snap = Snapshot(t=T0 + 130.0, state="running_depositing", job_name="block-slot", run_dir=None, layers_total=3,
                    passes_total=12, layer=1, pass_=2, passes_in_layer=4, layers_done=1, passes_done=6, arc_starts=7,
                    current_a=126.4, arc_on=True, voltage_v=18.72, wfs_m_min=5.8, temperature_c=171.0, interpass_limit_c=150.0,
                    position=(31.5, 17.0, 2.4), links=links, alarms=alarms,
                    allowed_commands=("pause", "abort", "estop"), message="")
    snap = Snapshot(**{**snap.__dict__, **snap_changes})
    hist = tuple(Sample(T0 + 100 + k * 0.1, 120 + 6 * math.sin(k / 5), 18.5 + 0.4 * math.sin(k / 7),
                        5.8 if k % 40 > 5 else 0.0, 140 + k * 0.25) for k in range(120))
    align = {"planes": [
        {"name": "top", "n_points": 5, "normal": [0.01396, -0.00873, 0.99986], "rms_mm": 0.0017,
         "max_residual_mm": 0.0029, "outliers": [],
         "points": [[10, 10, 20.12], [90, 10, 20.24], [90, 90, 19.96], [10, 90, 19.84], [50, 50, 20.04]],
         "residuals": [0.0012, -0.0021, 0.0029, -0.0008, -0.0012]},
        {"name": "side", "n_points": 3, "normal": [0.99966, 0.02618, 0.0], "rms_mm": 0.0011,
         "max_residual_mm": 0.0015, "outliers": [],
         "points": [[0.4, 20, 10], [0.9, 50, 12], [1.7, 80, 10]], "residuals": [0.0007, -0.0015, 0.0008]}],
        "level_a_deg": 0.5, "level_b_deg": -0.8, "face_angle_deg": 1.5,
        "transform": [[0.99966, -0.02618, 0.0, 1.2], [0.02618, 0.99966, 0.0, -0.4], [0.0, 0.0, 1.0, 0.1],
                      [0.0, 0.0, 0.0, 1.0]]}
    return View(snap=snap, seq=4242, history=hist, plan=PlanStatus("done", "jobs/block-slot.json"),
                job=job_info(load_job(recorded_job()), "block-slot"), alignment=align, platform="cnc", can_probe=True,
                devices=tuple(_dev(ls) for ls in links), sim=True)


def _dev(ls: LinkStat):  # type: ignore[no-untyped-def]
    from controller.tui.session import DeviceInfo

    err = "power source (Modbus TCP) at tcp://127.0.0.1:47603: no reply within 50 ms" if ls.errors else None
    return DeviceInfo(ls.device, ls.url, ls.connected, ls.frames_tx, ls.frames_rx, ls.errors, ls.queue_free, err)


def recorded_log() -> list[LogRow]:
    msgs = [("transition", "ready", "idle -> ready on open_job", None, None),
            ("info", "ready", "run 1: 12 passes to deposit", None, None),
            ("transition", "running_wait", "ready -> running_wait on start", 0, 0),
            ("transition", "running_depositing", "running_arc_start -> running_depositing on arc_on", 0, 0),
            ("info", "running_wait", "interpass wait: part at 162 °C, limit 150 °C", 1, None),
            ("alarm", "fault", "door opened during the build", 1, 2),
            ("transition", "idle", "fault -> idle on reset", None, None)]
    return [LogRow(i + 1, T0 + 10.0 * i, kind, st, msg, la, pa) for i, (kind, st, msg, la, pa) in enumerate(msgs)]

