"""The wire melting rate WFS = α·I + β·L·I² (core/melting.py) and `cell process stickout-fit`."""
from __future__ import annotations

import json

import numpy as np
import pytest

from controller.cli.main import main
from core.config import load_material
from core.errors import InputError
from core.melting import (calibrate, calibrate_on_line, current_at, current_for, fit_sweep, relation_for,
                          sensitivity_a_per_mm, stick_out_at, stick_out_for, synergic_current, wfs_for)

STEEL = load_material("er70s6-1.2mm")
INCONEL = load_material("inconel718-1.0mm")


def test_forward_and_inverse_round_trip():
    a, b = calibrate(200.0, 6.0, 15.0, 0.4)
    for L in (8.0, 15.0, 25.0):
        for W in (3.0, 6.0, 9.0):
            i = current_for(a, b, W, L)
            assert wfs_for(a, b, i, L) == pytest.approx(W, rel=1e-12)
            assert stick_out_for(a, b, W, i) == pytest.approx(L, rel=1e-9)


def test_calibration_puts_the_share_on_the_resistive_term():
    a, b = calibrate(200.0, 6.0, 15.0, 0.35)
    assert b * 15.0 * 200.0 ** 2 / 6.0 == pytest.approx(0.35)
    assert a * 200.0 / 6.0 == pytest.approx(0.65)


def test_steel_about_3_amperes_per_mm_near_200_a():
    rel = calibrate_on_line(STEEL.ribeiro, 15.0, 0.4)
    wfs = (200.0 - STEEL.ribeiro.i_min_a) * (STEEL.ribeiro.wfs_max_m_min - STEEL.ribeiro.wfs_min_m_min) / (
        STEEL.ribeiro.i_max_a - STEEL.ribeiro.i_min_a) + STEEL.ribeiro.wfs_min_m_min
    s = sensitivity_a_per_mm(rel, STEEL.ribeiro, wfs)
    assert -5.0 < s < -2.0, s                      # order of 3 A/mm (Lesnewich; docs/contract.md §6b)
    # finite difference agrees with the derivative
    d = (current_at(rel, STEEL.ribeiro, wfs, 16.0) - current_at(rel, STEEL.ribeiro, wfs, 14.0)) / 2.0
    assert d == pytest.approx(s, rel=0.02)


@pytest.mark.parametrize("mat", [STEEL, INCONEL], ids=["steel", "inconel"])
def test_anchored_current_is_the_synergic_line_at_nominal_for_every_wfs(mat):
    rel = relation_for(mat)
    r = mat.ribeiro
    for wfs in np.linspace(r.wfs_min_m_min, r.wfs_max_m_min, 7):
        assert current_at(rel, r, float(wfs), rel.stick_out_mm) == synergic_current(r, float(wfs))
        assert current_at(rel, r, float(wfs), rel.stick_out_mm + 3.0) < synergic_current(r, float(wfs))
        i = current_at(rel, r, float(wfs), 19.3)
        assert stick_out_at(rel, r, float(wfs), i) == pytest.approx(19.3, abs=1e-9)


def test_fit_sweep_recovers_alpha_beta():
    rng = np.random.default_rng(3)
    a, b = 0.0268, 9.35e-6
    L = np.repeat([10.0, 13.0, 16.0, 20.0], 3)
    i = np.tile([110.0, 130.0, 150.0], 4)
    W = np.array([wfs_for(a, b, float(x), float(y)) for x, y in zip(i, L)]) + rng.normal(0, 0.002, L.size)
    f = fit_sweep(L, W, i)
    assert f.alpha == pytest.approx(a, rel=0.01) and f.beta == pytest.approx(b, rel=0.03)
    assert f.r2 > 0.999 and f.rms < 0.005 and f.rms_stick_out_mm < 0.2


def test_fit_sweep_refuses_a_sweep_that_cannot_separate_alpha_and_beta():
    with pytest.raises(InputError, match="at least 3"):
        fit_sweep([15, 15], [5, 6], [120, 140])
    with pytest.raises(InputError, match="positive"):
        fit_sweep([15, 15, -1], [5, 6, 7], [120, 140, 150])


def test_cli_stickout_fit(tmp_path, capsys):
    a, b = 0.0268, 9.35e-6
    rows = ["stick_out_mm,wfs_m_min,current_a"]
    for L in (10, 15, 20):
        for i in (110, 140):
            rows.append(f"{L},{wfs_for(a, b, i, L):.6f},{i}")
    p = tmp_path / "sweep.csv"
    p.write_text("\n".join(rows) + "\n")
    assert main(["process", "stickout-fit", str(p), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"alpha", "beta", "r2", "rms"} <= set(out)
    assert out["alpha"] == pytest.approx(a, rel=1e-4) and out["beta"] == pytest.approx(b, rel=1e-3)
    bad = tmp_path / "bad.csv"
    bad.write_text("stick_out_mm,current_a\n15,120\n")
    assert main(["process", "stickout-fit", str(bad)]) == 2
    assert "missing column 'wfs_m_min'" in capsys.readouterr().err
