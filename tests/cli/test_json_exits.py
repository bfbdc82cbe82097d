"""Issue 38 item 3 / issue 36 item 8: every `--json` command prints exactly one JSON object on every
exit path (bad input, usage errors, refusals, faults), with the documented exit code; a refusal
that needs no device comes before the first motion (docs/contract.md §6, §7; docs/controller.md).
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from controller.cli.main import main
from controller.harness.repair_parts import make_parts


def _one_object(capsys: pytest.CaptureFixture[str], argv: list[str]) -> tuple[int, dict, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 1, (argv, out, err)
    obj = json.loads(lines[0])
    assert isinstance(obj, dict), (argv, obj)
    return code, obj, err


def _failures(tmp: Path) -> list[list[str]]:
    """One failing invocation of each `--json` command of the §7 table (and the journal's)."""
    missing = str(tmp / "missing")
    bad_csv = tmp / "bad.csv"
    bad_csv.write_text("x,y\n1,oops\n", encoding="utf-8")
    return [
        ["process", "inverse", "--width", "-3", "--json"],
        ["process", "forward", "--current", "100", "--json"],               # usage: --speed missing
        ["process", "fit", missing, "--json"],
        ["bead", "critical-distance", "--model", "bogus", "--json"],
        ["bead", "fit", str(bad_csv), "--json"],
        ["plan", missing, "--width", "5", "--json"],
        ["align", "plane", missing, "--json"],
        ["align", "transform", "--rotate", "Q:5", "--pivot", "0,0,0", missing, "--json"],
        ["repair", "plan", missing, "--stock", missing, "--width", "4", "--json"],
        ["repair", "run", missing, "--json"],
        ["run", missing, "--json"],
        ["resume", "--run", missing, "--json"],
        ["report", missing, "--json"],
        ["export", missing, "--format", "gcode", "--json"],
        ["finish", "plan", missing, "--json"],
        ["finish", "plan", missing, "--tool", "nope", "--json"],
        ["journal", "check", missing, "--json"],
        ["demo", "--json", "--no-such-option"],
    ]


def test_every_json_command_prints_one_object_on_its_failure_paths(tmp_path: Path, capsys) -> None:
    for argv in _failures(tmp_path):
        code, obj, err = _one_object(capsys, argv)
        assert code == 2, (argv, code, err)
        assert obj["exit_code"] == 2 and obj["state"] == "refused", (argv, obj)
        assert err.startswith("error: ") and obj["error"] and obj["error"] in err, (argv, obj, err)


def _repair_job(tmp: Path, capsys) -> Path:
    cad, stock = make_parts(tmp)
    job = tmp / "pocket.repair.job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--out", str(job), "--json"]) == 0
    capsys.readouterr()
    return job


def test_repair_run_refuses_a_time_scale_the_link_cannot_feed_before_any_device(tmp_path: Path, capsys) -> None:
    """Against `cell sim up` at the shipped time scale: refused before the CNC is even opened (its
    URL has nothing listening here: had the command connected first, the error would say so)."""
    job = _repair_job(tmp_path, capsys)
    code, obj, err = _one_object(capsys, ["repair", "run", str(job), "--json"])
    assert code == 2 and obj["state"] == "refused", (obj, err)
    assert "run the simulators at time scale" in obj["error"] and "restart `cell sim up`" in obj["error"], obj
    assert "unreachable" not in err and "no answer" not in err, err


def test_a_fault_during_alignment_exits_1_with_its_object(tmp_path: Path, capsys) -> None:
    """`cell align run --sim --json` whose probe move never ends: exit 1 (not the bad-input code)
    and the one object names the fault."""
    sim_yaml = tmp_path / "sim.yaml"
    sim = yaml.safe_load(Path("config/sim.yaml").read_text(encoding="utf-8"))
    sim["faults"] = "freeze@probe=1"
    sim_yaml.write_text(yaml.safe_dump(sim), encoding="utf-8")
    code, obj, err = _one_object(capsys, ["align", "run", "--sim", "--sim-config", str(sim_yaml), "--json"])
    assert code == 1 and obj["exit_code"] == 1 and obj["state"] == "fault", (obj, err)
    assert "in probing" in obj["error"] and "motion held, spindle and laser off" in obj["error"], obj
