"""The path loop (issue 35, `process_control: {mode: path}`, docs/closed-loop.md "Along the path"):
sensing along the pass, learning by position, per-segment speeds in the run's working copy
(journaled, re-applied on resume), the pause, and the record's heights along the path."""
from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pytest

from bench.closed_loop import wall_job
from bench.path_loop import beads_of, build
from controller.journal.store import Journal
from controller.runtime.work import WorkItem
from controller.runtime.layer_control import LayerControl
from core.config import ProcessControl, load_material
from core.melting import current_at, relation_for
from controller.job.model import CellJob
from tests.jobs import JobSpec, PassSpec, small_job

MAT = load_material("inconel718-1.0mm")


def _job(n: int, h: float = 0.77) -> CellJob:
    """A single-bead wall 30 mm long, `n` layers, alternating direction."""
    ends = [[0.0, 0.0], [30.0, 0.0]]
    layers = [[PassSpec(ends if i % 2 == 0 else ends[::-1], speed=1500.0, wfs=6.9, current=151.0, width=7.0)]
              for i in range(n)]
    return small_job(layers, JobSpec(material=MAT.name, layer_height=h, width=7.0, step_over=5.0, name="wall"))


async def _lay(lc: LayerControl, la: int, top_at: Callable[[float], float]) -> str | None:
    """Layer la as the robot would report it: samples along the pass whose current says the top."""
    rel = relation_for(MAT)
    p = lc.pass_for(la, 0)
    z = float(p.points[0][2])
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p.points[:, :2], axis=0).T))])
    wfs = p.wire_feeds()
    for s in np.linspace(0.0, float(cum[-1]), 60):
        x = float(np.interp(s, cum, p.points[:, 0]))
        k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(wfs) - 1)   # the feed of the move there
        lc.arc_sample(la, 0, float(s), current_at(rel, MAT.ribeiro, float(wfs[k]), 15.0 + z - top_at(x)))
    lc.bead_closed(la, 0, [current_at(rel, MAT.ribeiro, 6.9, 15.0 + z - top_at(15.0))] * 10, 6.9)
    work = [WorkItem(i, 0) for i in range(len(lc.layers))]
    return (await lc.after_pass(work[la], work[la + 1:])).pause


async def test_a_low_stretch_is_slowed_where_it_lies_and_a_resume_lays_the_same_speeds(tmp_path: Path):
    job = _job(6)
    cfg = ProcessControl(mode="path")
    j = Journal(tmp_path / "journal.sqlite")
    j.start_job("h", "wall", "robot", "{}")
    lc = LayerControl(job=job, cfg=cfg, material=MAT, platform="robot", journal=j)
    for la in range(3):   # the stretch x > 20 rises 0.6 of the rest a layer
        assert await _lay(lc, la, lambda x, la=la: 0.77 * (la + 1) * (0.6 if x > 20 else 1.0)) is None
    p3 = lc.pass_for(3, 0)
    assert p3.seg_speed_mm_min is not None                       # cell-job/2 arrays in the working copy
    mid = 0.5 * (p3.points[1:, 0] + p3.points[:-1, 0])
    sp = p3.speeds()
    assert float(np.mean(sp[mid > 23])) < 0.9 * float(np.mean(sp[mid < 15]))   # slower where it is low
    assert np.hypot(*np.diff(p3.points[:, :2], axis=0).T).max() <= 3.5 + 1e-9  # half a bead width a segment
    assert job.layers[3].passes[0].seg_speed_mm_min is None      # the job itself is not rewritten
    kinds = [k for (k,) in j.query("SELECT kind FROM events WHERE kind LIKE 'path%' ORDER BY id")]
    assert kinds.count("path") == 3 and kinds.count("path_plan") == 4
    j.close()
    j2 = Journal(tmp_path / "journal.sqlite")
    lc2 = LayerControl(job=job, cfg=cfg, material=MAT, platform="robot", journal=j2)
    lc2.restore()
    assert np.allclose(lc2.pass_for(3, 0).speeds(), sp, rtol=1e-6)   # the same speeds after a restart
    assert np.allclose(lc2.pass_for(3, 0).points, p3.points)
    j2.close()


async def test_a_step_in_the_metal_splits_the_next_layers_there_and_a_resume_splits_them_the_same(tmp_path: Path):
    job = _job(8)
    cfg = ProcessControl(mode="path", path_edges=True)
    j = Journal(tmp_path / "journal.sqlite")
    j.start_job("h", "wall", "robot", "{}")
    lc = LayerControl(job=job, cfg=cfg, material=MAT, platform="robot", journal=j)
    for la in range(6):   # past x 15 each layer lays 0.6 of the rest (docs/closed-loop.md "Region edges")
        await _lay(lc, la, lambda x, la=la: 0.77 * (la + 1) * (0.6 if x > 15.0 else 1.0))
    p6 = lc.pass_for(6, 0)
    assert np.min(np.abs(p6.points[:, 0] - 15.0)) < 1.0          # a segment ends at the edge
    assert np.min(np.abs(lc.pass_for(2, 0).points[:, 0] - 15.0)) > 1.0   # not before it was seen
    plans = [json.loads(m) for (m,) in j.query("SELECT message FROM events WHERE kind = 'path_plan' ORDER BY id")]
    assert plans[-1]["cuts"] and abs(plans[-1]["cuts"][0][0] - 15.0) < 1.0
    j.close()
    j2 = Journal(tmp_path / "journal.sqlite")
    lc2 = LayerControl(job=job, cfg=cfg, material=MAT, platform="robot", journal=j2)
    lc2.restore()
    assert np.allclose(lc2.pass_for(6, 0).points, p6.points)     # the same points after a restart
    assert np.allclose(lc2.pass_for(6, 0).speeds(), p6.speeds(), rtol=1e-6)
    j2.close()


async def test_a_stretch_the_bound_cannot_level_pauses_before_the_next_layer(tmp_path: Path):
    j = Journal(tmp_path / "journal.sqlite")
    j.start_job("h", "wall", "robot", "{}")
    lc = LayerControl(job=_job(6), cfg=ProcessControl(mode="path", speed_trim_pct=10), material=MAT,
                      platform="robot", journal=j)
    why = None
    for la in range(5):   # the stretch x > 20 gets a third of the metal: 10 % of speed cannot follow
        why = await _lay(lc, la, lambda x, la=la: 0.77 * (la + 1) * (0.33 if x > 20 else 1.0))
        if why:
            break
    assert why is not None and "speed_trim_pct 10" in why and "off the layer's mean" in why
    j.close()


async def test_with_the_wire_feed_a_low_stretch_is_laid_slower_at_less_wire_keeping_the_width_and_a_resume_lays_it_again(
        tmp_path: Path):
    job = _job(6)
    cfg = ProcessControl(mode="path", path_speed_range=(0.3, 2.0), path_wfs_trim_pct=40, path_max_error_mm=50)
    j = Journal(tmp_path / "journal.sqlite")
    j.start_job("h", "wall", "robot", "{}")
    lc = LayerControl(job=job, cfg=cfg, material=MAT, platform="robot", journal=j)
    for la in range(3):   # the stretch x > 20 rises 0.6 of the rest a layer
        await _lay(lc, la, lambda x, la=la: 0.77 * (la + 1) * (0.6 if x > 20 else 1.0))
    p3 = lc.pass_for(3, 0)
    mid = 0.5 * (p3.points[1:, 0] + p3.points[:-1, 0])
    sp, wf = p3.speeds(), p3.wire_feeds()
    assert p3.seg_wfs_m_min is not None
    low, rest = mid > 24, mid < 15
    assert float(sp[low].mean()) < 0.85 * float(sp[rest].mean())           # slower where it is low
    assert float(wf[low].mean()) < float(wf[rest].mean()) - 0.1 and wf.min() >= 6.9 * 0.6 - 1e-6   # less wire, within the trim
    assert wf.max() <= MAT.ribeiro.wfs_max_m_min + 1e-9                      # and the synergic envelope
    law = lc.path.bead if lc.path is not None else None
    assert law is not None
    inside = (wf > 6.9 * 0.6 + 1e-3) & (wf < MAT.ribeiro.wfs_max_m_min - 1e-3)
    assert inside.any()
    # the planned width (the layer loop's trim laid the same way)
    assert np.allclose(law.width(wf[inside], sp[inside]), law.width(np.full(1, 6.9), np.full(1, 1500.0)), rtol=2e-3)
    j.close()
    j2 = Journal(tmp_path / "journal.sqlite")
    lc2 = LayerControl(job=job, cfg=cfg, material=MAT, platform="robot", journal=j2)
    lc2.restore()
    assert np.allclose(lc2.pass_for(3, 0).wire_feeds(), wf, rtol=1e-6)     # the same wire feeds after a restart
    assert np.allclose(lc2.pass_for(3, 0).speeds(), sp, rtol=1e-6)
    j2.close()


@pytest.mark.realtime
def test_a_short_wall_in_path_mode_lays_the_learned_speeds_and_records_the_heights(tmp_path: Path,
                                                                                   monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("CELL_RECORD_PLOTS", "1")
    job = wall_job(4, 40.0)
    out = asyncio.run(build(job, part="wall", gain=1.0, mode="path", tmp=tmp_path, scale=30.0, keep=tmp_path / "keep"))
    assert out["state"] == "complete", out["paused"]
    rec = tmp_path / "keep" / "wall-1.0-path"
    report = json.loads((rec / "report.json").read_text())
    assert [r["layer"] for r in report["path"]["layers"]][:4] == [0, 1, 2, 3]
    rows = (rec / "path.csv").read_text().splitlines()
    assert rows[0].startswith("layer,x_mm,y_mm,along_mm,measured_top_mm") and len(rows) > 4 * 3
    assert (rec / "path.png").stat().st_size > 10_000
    # the robot executed the working copy's per-segment speeds: deposit.jsonl's segment speeds
    # in the last layer vary as its journaled factors do
    segs = [json.loads(x) for x in (rec / "sim" / "deposit.jsonl").read_text().splitlines()]
    last = beads_of(segs)[-1]
    v = [math.dist(s["from"][:2], s["to"][:2]) / (s["t1"] - s["t0"]) * 60.0 for s in last if s["t1"] > s["t0"]]
    assert max(v) / min(v) > 1.02


def test_the_build_screen_shows_the_path_loop_line():
    from controller.runtime.events import Snapshot
    from controller.tui.build import process_text

    s = Snapshot().with_(stick_out_mm=15.2, path_rms_mm=0.18, path_spread_mm=0.62, path_factor_min=0.81,
                         path_factor_max=1.12)
    lines = process_text(s).strip().splitlines()
    assert lines[-1] == "along the path: RMS 0.18 mm · spread 0.62 mm · speed × 0.81–1.12"
    assert "along the path" not in process_text(Snapshot().with_(stick_out_mm=15.2))


@pytest.mark.realtime
async def test_an_opc_ua_client_reads_the_path_loop_values():
    import socket

    from asyncua import Client

    from controller.opcua.endpoint import Identification
    from controller.opcua.server import FactoryServer
    from controller.runtime.events import EventBus
    from core.config import OpcUaSettings

    sk = socket.socket()
    sk.bind(("127.0.0.1", 0))
    endpoint = f"opc.tcp://127.0.0.1:{sk.getsockname()[1]}/cell"
    sk.close()
    bus = EventBus()
    srv = FactoryServer(OpcUaSettings(enabled=True, endpoint=endpoint), cell_name="c",
                        identification=Identification("m", "m", "s", "r"), bus=bus, control=None)
    srv.start()
    try:
        bus.update(path_rms_mm=0.21, path_spread_mm=0.7, path_factor_min=0.8, path_factor_max=1.1)
        async with Client(endpoint) as client:
            ns = await client.get_namespace_index("urn:cell-controller:machines")
            proc = await client.nodes.objects.get_child([f"{ns}:Machines", f"{ns}:c", f"{ns}:Monitoring", f"{ns}:Process"])
            got = {}
            for name in ("PathHeightRms", "PathHeightSpread", "PathSpeedFactorMin", "PathSpeedFactorMax"):
                node = await proc.get_child([f"{ns}:{name}"])
                for _ in range(50):   # the server publishes the bus on its own loop
                    got[name] = await node.read_value()
                    if got[name] == got[name]:   # not NaN
                        break
                    await asyncio.sleep(0.05)
    finally:
        srv.stop()
    assert got == {"PathHeightRms": 0.21, "PathHeightSpread": 0.7, "PathSpeedFactorMin": 0.8, "PathSpeedFactorMax": 1.1}


async def test_the_cnc_probes_along_every_pass_and_slows_where_the_probe_found_it_low(tmp_path: Path):
    seen: list[list[tuple[float, float, float]]] = []

    async def probe(la: int, spots: Sequence[tuple[float, float, float]]) -> list[float]:
        seen.append(list(spots))   # the touch probe: the stretch x > 20 is 0.5 mm low
        return [z - (0.5 if x > 20 else 0.0) for x, _y, z in spots]

    j = Journal(tmp_path / "journal.sqlite")
    j.start_job("h", "wall", "cnc", "{}")
    lc = LayerControl(job=_job(6), cfg=ProcessControl(mode="path", probe_spacing_mm=5.0), material=MAT,
                      platform="cnc", journal=j, probe=probe)
    work = [WorkItem(i, 0) for i in range(6)]
    for la in range(2):
        lc.pass_for(la, 0)
        assert (await lc.after_pass(work[la], work[la + 1:])).pause is None
    xs = sorted(x for x, _y, _z in seen[0])
    assert xs[0] == pytest.approx(1.75) and xs[-1] == pytest.approx(28.25) and len(xs) == 6   # ends a quarter width in
    p2 = lc.pass_for(2, 0)
    mid = 0.5 * (p2.points[1:, 0] + p2.points[:-1, 0])
    assert float(np.mean(p2.speeds()[mid > 24])) < 0.95 * float(np.mean(p2.speeds()[mid < 16]))
    j.close()
