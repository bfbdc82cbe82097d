"""Simulated time that adapts (issue 38 item 4, issue 36 item 8): against `cell sim up` in a process of
its own, a command whose program the host cannot feed at cell.yaml's time scale lowers the
simulators' clock to the highest scale it can feed, says so before any motion and in its record,
and gives the clock back afterwards (docs/controller.md, "Simulated time the host can feed")."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from controller.cli.main import main
from controller.harness.repair_parts import make_parts, posed_sim
from controller.harness.sim_clock import SimClockLink
from tests.sim_processes import free_ports, read_devices

pytestmark = [pytest.mark.realtime, pytest.mark.timeout(180)]

ROOT = Path(__file__).resolve().parents[2]


def _cnc_cell(tmp: Path, scale: float = 60.0) -> Path:
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    p = free_ports(4)
    cfg["cell"]["platform"] = "cnc"
    cfg["cell"]["time_scale"] = scale
    cfg["devices"]["robot"]["url"] = f"socket://127.0.0.1:{p[0]}"
    cfg["devices"]["cnc"]["url"] = f"socket://127.0.0.1:{p[1]}"
    cfg["devices"]["power_source"]["url"] = f"tcp://127.0.0.1:{p[2]}"
    cfg["devices"]["cellio"]["url"] = f"tcp://127.0.0.1:{p[3]}"
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    for name in ("materials", "power_source.dbc"):   # what cell.yaml names beside it
        os.symlink(ROOT / "config" / name, tmp / name)
    return path


def test_repair_run_against_sim_up_lowers_the_clock_for_the_build_and_gives_it_back(tmp_path: Path, capsys) -> None:
    cad, stock = make_parts(tmp_path)
    job = tmp_path / "pocket.repair.job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--out", str(job), "--json"]) == 0
    capsys.readouterr()
    cell = _cnc_cell(tmp_path)
    # the stock posed on the table as `cell demo --repair` poses it
    sim = posed_sim(stock, 1.2, -0.8, 3.0, (2.0, -1.5, 0.5))
    (tmp_path / "posed-sim.yaml").write_text(yaml.safe_dump(sim.model_dump(mode="json")))
    proc = subprocess.Popen([sys.executable, "-m", "controller.cli.main", "sim", "up", "--cell-config", str(cell),
                             "--config", str(tmp_path / "posed-sim.yaml"), "--log", str(tmp_path / "logs")],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        read_devices(proc)   # the device lines come once every simulator (and the clock) is up
        clock = SimClockLink.find(yaml.safe_load(cell.read_text())["devices"]["cnc"]["url"])
        assert clock is not None and clock.scale() == 60.0   # `cell sim up` names its clock
        code = main(["repair", "run", str(job), "--cell-config", str(cell), "--no-finish", "--json",
                     "--runs", str(tmp_path / "runs")])
        out, err = capsys.readouterr()
        rep = json.loads(out)
        after = clock.scale()
    finally:
        proc.terminate()
        proc.wait(20)
    # said before any motion (stderr's first line), and in the record
    assert err.splitlines()[0].startswith("cnc: at time scale 60 the link cannot feed"), err
    assert "the simulators of `cell sim up` now run at" in err.splitlines()[0]
    assert code in (0, 1) and rep["build"]["state"] == "complete", (code, rep.get("error"), err[-800:])
    assert rep["time_scale"] < 60.0 and rep["time_scale_probing"] == 60.0
    assert any("time scale limited to" in n for n in rep["notes"])
    assert after == 60.0          # the configured scale given back
    # the simulators' own record: metal was laid (the build ran at the lowered scale)
    deposits = (tmp_path / "logs" / "deposit.jsonl").read_text().splitlines()
    assert len(deposits) > 10


def test_without_a_clock_the_command_refuses_before_any_device(tmp_path: Path, capsys) -> None:
    """Nothing serves the cell's CNC (hardware, or an older `cell sim up`): refused, exit 2, before
    the CNC is even opened (had it connected first, the error would name the unreachable URL)."""
    cad, stock = make_parts(tmp_path)
    job = tmp_path / "pocket.repair.job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--out", str(job), "--json"]) == 0
    capsys.readouterr()
    cell = _cnc_cell(tmp_path)
    code = main(["repair", "run", str(job), "--cell-config", str(cell), "--json", "--runs", str(tmp_path / "runs")])
    obj = json.loads(capsys.readouterr().out)
    assert code == 2 and "name no clock to lower" in obj["error"] and "unreachable" not in obj["error"], obj
