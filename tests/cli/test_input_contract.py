"""The CLI contract on the paths issue 14 found broken: one `error:` line naming the file, field
or device, exit 2, no traceback, bounded time; `--json` output valid JSON."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.cli.main import main
from core.config import CONFIG_DIR


def _call(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    c = capsys.readouterr()
    assert "Traceback" not in c.err
    return rc, c.out, c.err


def _one_error(rc: int, err: str, *needles: str) -> None:
    assert rc == 2
    assert err.startswith("error: ") and err.count("\n") == 1, err
    for n in needles:
        assert n in err, err


@pytest.mark.parametrize("url, needle", [
    ("socket://127.0.0.1:99999", "Port out of range"),
    ("tcp://[::1", "Invalid IPv6 URL"),
    ("socket://:5000", "without a host"),
])
def test_bad_device_urls_in_cell_yaml_name_the_device(tmp_path: Path, capsys, url: str, needle: str) -> None:
    text = (CONFIG_DIR / "cell.yaml").read_text(encoding="utf-8").replace("socket://127.0.0.1:47601", url, 1)
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(text, encoding="utf-8")
    job = tmp_path / "job.json"
    job.write_text("{}")
    rc, _, err = _call(capsys, "run", str(job), "--cell-config", str(cfg))
    _one_error(rc, err, str(cfg), "devices.robot.url", needle)


def test_a_material_with_an_infinite_coefficient_is_refused(tmp_path: Path, capsys) -> None:
    text = (CONFIG_DIR / "materials" / "inconel718-1.0mm.yaml").read_text(encoding="utf-8")
    lines = [("  k1: .inf" if ln.strip().startswith("k1:") else ln) for ln in text.splitlines()]
    mat = tmp_path / "m.yaml"
    mat.write_text("\n".join(lines) + "\n", encoding="utf-8")
    rc, _, err = _call(capsys, "process", "inverse", "--width", "7", "--material", str(mat), "--allow-outside", "--json")
    _one_error(rc, err, str(mat), "ribeiro.k1")


def _box(path: Path, scale: float = 1.0, far: float | None = None) -> Path:
    m = trimesh.creation.box(extents=(20, 20, 10))
    m.apply_translation((0, 0, 5))
    m.apply_scale(scale)
    if far is not None:
        m.vertices[0] = (far, 0, 0)
    m.export(path)
    return path


def test_an_stl_with_1e30_coordinates_is_refused(tmp_path: Path, capsys) -> None:
    f = _box(tmp_path / "far.stl", far=1e30)
    rc, _, err = _call(capsys, "plan", str(f), "--width", "7", "--out", str(tmp_path / "o.json"))
    _one_error(rc, err, "far.stl", "1e+30")


def test_a_part_larger_than_the_workspace_is_refused_before_slicing(tmp_path: Path, capsys) -> None:
    f = _box(tmp_path / "big.stl", scale=100.0)  # 2 m x 2 m x 1 m: beyond the 1 m workspace
    t0 = time.monotonic()
    rc, _, err = _call(capsys, "plan", str(f), "--width", "7", "--out", str(tmp_path / "o.json"))
    _one_error(rc, err, "big.stl", "larger than the workspace")
    assert time.monotonic() - t0 < 10.0


def test_align_plane_with_coordinates_near_1e160_returns_at_once(tmp_path: Path, capsys) -> None:
    f = tmp_path / "p.csv"
    f.write_text("x,y,z\n" + "".join(f"{x}e159,{y}e159,{x * y}e158\n" for x in range(1, 4) for y in range(1, 4)))
    t0 = time.monotonic()
    rc, _, err = _call(capsys, "align", "plane", str(f), "--json")
    _one_error(rc, err, "absurdly scaled")
    assert time.monotonic() - t0 < 5.0


def test_align_plane_of_a_non_utf8_csv(tmp_path: Path, capsys) -> None:
    f = tmp_path / "latin1.csv"
    f.write_bytes("x,y,z\n0,0,0\n1,0,0\n0,1,0\n1,1,0.01\n# Größe\n".encode("latin-1"))
    rc, _, err = _call(capsys, "align", "plane", str(f))
    _one_error(rc, err, "latin1.csv", "UTF-8")


def test_process_fit_json_never_prints_nan(tmp_path: Path, capsys) -> None:
    f = tmp_path / "fit.csv"
    rows = ["current_a,speed_mm_min,width_mm,height_mm"]
    rows += [f"{i},{s},1e300,1e-300" for i in (100, 130, 160) for s in (300, 500)]
    f.write_text("\n".join(rows) + "\n")
    rc, out, err = _call(capsys, "process", "fit", str(f), "--json")
    if rc == 0:
        json.loads(out, parse_constant=lambda c: pytest.fail(f"--json printed {c}"))
    else:
        _one_error(rc, err, "fit.csv")


def test_bead_fit_of_a_flat_profile_is_refused(tmp_path: Path, capsys) -> None:
    f = tmp_path / "flat.csv"
    x = np.linspace(-5, 5, 41)
    f.write_text("x_mm,y_mm\n" + "".join(f"{v:.3f},1.0\n" for v in x))
    rc, out, err = _call(capsys, "bead", "fit", str(f), "--json")
    _one_error(rc, err, "flat.csv")
    assert out.count("\n") == 1 and json.loads(out)["state"] == "refused"   # --json: one object (issue 38)
    # a plateau on a substrate: the fits would answer a bead kilometres wide
    f.write_text("x_mm,y_mm\n" + "".join(f"{v:.3f},{1.0 if abs(v) < 3 else 0.0}\n" for v in x))
    rc, out, err = _call(capsys, "bead", "fit", str(f), "--json")
    assert rc == 2 or all(d["width_mm"] < 30 for d in json.loads(out).values())
