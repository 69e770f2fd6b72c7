"""The inertia table (hailstorm.runtime.inertia.table): its interpolation rule, the shipped table
against the peer, the factors it gives against direct runs, its cache."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hailstorm.runtime.inertia import factors as factors_module
from hailstorm.runtime.inertia import impact_inertia, inertia_factors
from hailstorm.runtime.inertia import table as tm
from hailstorm.runtime.inertia.impact import ICE_DENSITY
from hailstorm.runtime.inertia.pad import PAD_DENSITY

E, NU = 2e6, 0.35
RATIO = tm.mass_ratio_key(ICE_DENSITY / PAD_DENSITY)


def _stone(R):
    return ICE_DENSITY * 4.0 / 3.0 * math.pi * np.asarray(R) ** 3


def test_interpolation_is_exact_for_cubics_and_refuses_outside():
    """A table holding a bicubic in (log R/h, log v/c) gives it back anywhere in the grid, to
    rounding, at the edges' one-sided stencils too; outside the grid, a NaN in the stencil, or
    a non-finite query: NaN (a direct run)."""
    ls, lv = np.linspace(-3.0, 0.7, 9), np.linspace(-6.0, -1.2, 11)

    def f(x, y):
        return 1.0 + 0.1 * x - 0.02 * x**3 + 0.03 * x * y**2 - 0.001 * y**3

    X, Y = np.meshgrid(ls, lv, indexing="ij")
    fac = np.stack([f(X, Y), 2 * f(X, Y), f(X, Y) ** 0, -f(X, Y)])
    tab = tm.InertiaTable(NU, RATIO, ls, lv, fac)
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(ls[0], ls[-1], 200), [ls[0], ls[-1], ls[0] + 1e-3]])
    y = np.concatenate([rng.uniform(lv[0], lv[-1], 200), [lv[0], lv[-1], lv[-1] - 1e-3]])
    got = tab.lookup(np.exp(x), np.exp(y))
    np.testing.assert_allclose(got[0], f(x, y), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got[1], 2 * f(x, y), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got[2], 1.0, rtol=1e-12)
    out = tab.lookup([math.exp(ls[0] - 0.01), 0.1, np.nan, 0.1], [0.01, math.exp(lv[-1] + 0.01), 0.01, -1.0])
    assert np.isnan(out).all()
    holed = fac.copy()
    holed[:, 4, 5] = np.nan
    probe = tab.lookup([math.exp(ls[4] + 0.1), math.exp(ls[0] + 0.01)], [math.exp(lv[5] + 0.1), math.exp(lv[0])])
    hole = tm.InertiaTable(NU, RATIO, ls, lv, holed).lookup(
        [math.exp(ls[4] + 0.1), math.exp(ls[0] + 0.01)], [math.exp(lv[5] + 0.1), math.exp(lv[0])])
    assert np.isnan(hole[:, 0]).all() and np.array_equal(hole[:, 1], probe[:, 1])


def test_the_shipped_table_is_the_peers():
    """The default material's shipped table holds what the peer gives at its grid points
    (three of them, corner, middle and the fast small-stone corner, where the factors are
    farthest from 1): a stale table after a change to the peer fails here."""
    path = tm.shipped_path(NU, RATIO)
    assert path.exists(), "python -m hailstorm.runtime.inertia.table writes it"
    tab = tm.inertia_table(NU, RATIO)
    h, young, rho = tm.REFERENCE_THICKNESS, 1.0e6, 100.0
    c = tm.wave_speed(young, rho)
    for i, j in ((0, 0), (7, 6), (0, tab.log_speed.size - 1)):
        R = math.exp(tab.log_size[i]) * h
        m = RATIO * rho * 4.0 / 3.0 * math.pi * R**3
        want = impact_inertia(R, m, math.exp(tab.log_speed[j]) * c, h, young, NU, rho)
        np.testing.assert_allclose(tab.factors[:, i, j], want, rtol=1e-6)
    assert tab.factors[0, 0, -1] < 0.9  # a point with inertia to tabulate


def test_tabulated_factors_are_the_direct_ones_within_one_percent():
    """Twelve random impacts of the grid's range on the default foam, at the scene's modulus and a
    thickness the table was not built at: each factor within 1 % of a direct run (the peer's
    own scatter is 0.2 %, ``bench_inertia_table.py``'s 200 points reach 0.8 %); an impact off
    the grid (a stone wider than twice the layer) and one of another density are run directly
    and counted."""
    rng = np.random.default_rng(7)
    n, h = 12, 0.0117
    s = np.exp(rng.uniform(*np.log(tm.SIZE_RANGE), n))
    v = np.exp(rng.uniform(*np.log(tm.SPEED_RANGE), n)) * tm.wave_speed(E, PAD_DENSITY)
    R = np.append(s * h, [2.5 * h, 0.3 * h])
    m = np.append(_stone(s * h), [_stone(2.5 * h), 0.5 * _stone(0.3 * h)])
    v = np.append(v, [3.0, 3.0])
    hh = np.full(R.size, h)
    direct = np.array(inertia_factors(R, m, v, hh, E, NU, PAD_DENSITY, table=False).astuple())
    got = inertia_factors(R, m, v, hh, E, NU, PAD_DENSITY)
    assert got.direct_runs == 2 and got.direct[-2:].all() and not got.direct[:n].any()
    np.testing.assert_allclose(np.array(got.astuple())[:, :n], direct[:, :n], rtol=0.01)
    np.testing.assert_array_equal(np.array(got.astuple())[:, n:], direct[:, n:])


def test_a_new_material_is_computed_once_and_cached(tmp_path, monkeypatch):
    """A material without a shipped table: computed (on a 4 x 4 grid here, to be quick), written
    to the cache, read back bit for bit in a fresh process' place; a damaged file is computed
    anew; bad materials are refused."""
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(tm, "SIZE_POINTS", 4)
    monkeypatch.setattr(tm, "SPEED_POINTS", 4)
    monkeypatch.setattr(tm, "SPEED_RANGE", (0.01, 0.05))
    monkeypatch.setattr(tm, "_TABLES", {})
    calls = []
    build = tm.build_inertia_table
    monkeypatch.setattr(tm, "build_inertia_table", lambda *a, **k: calls.append(a) or build(*a, **k))
    first = tm.inertia_table(0.3, 5.0)
    files = list((tmp_path / "cache" / "inertia_table").glob("*.npz"))
    assert len(calls) == 1 and len(files) == 1 and first.factors.shape == (4, 4, 4)
    assert np.all(np.isfinite(first.factors))
    monkeypatch.setattr(tm, "_TABLES", {})  # a new process: nothing in memory
    again = tm.inertia_table(0.3, 5.0)
    assert len(calls) == 1
    np.testing.assert_array_equal(again.factors, first.factors)
    files[0].write_bytes(b"not a table")
    monkeypatch.setattr(tm, "_TABLES", {})
    tm.inertia_table(0.3, 5.0)
    assert len(calls) == 2 and np.load(files[0])["factors"].shape == (4, 4, 4)
    with pytest.raises(ValueError, match="poisson"):
        tm.inertia_table(0.5, 5.0)
    with pytest.raises(ValueError, match="mass ratio"):
        tm.inertia_table(0.3, -1.0)


def test_the_storm_reads_its_inertia_from_the_table(monkeypatch):
    """The storm's impacts (the default scene's stones and foam) are served by the shipped table:
    no direct run, and the summary says so."""
    from hailstorm.runtime.storm.limits import summarise

    calls = []
    monkeypatch.setattr(factors_module, "impact_inertia", lambda *a, **k: calls.append(a) or (1.0, 1.0, 1.0, 1.0))
    R = np.array([0.0025, 0.004, 0.008])
    got = inertia_factors(R, _stone(R), [12.0, 15.0, 20.0], [0.012, 0.015, 0.02], E, NU, PAD_DENSITY)
    assert not calls and got.direct_runs == 0 and np.all(got.force < 1.0)
    z = np.zeros(3)
    assert summarise(z, z, z, np.full(3, 0.015), inertia=got)["inertia_direct_runs"] == 0


def test_a_storm_computes_a_missing_table_only_when_it_pays(tmp_path, monkeypatch):
    """A material without a table: a storm of few impacts runs them directly (no table, nothing
    cached); one of at least ``BUILD_MIN_IMPACTS`` computes the table once and reads them from it."""
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(tm, "SIZE_POINTS", 4)
    monkeypatch.setattr(tm, "SPEED_POINTS", 4)
    monkeypatch.setattr(tm, "_TABLES", {})
    monkeypatch.setattr(factors_module, "BUILD_MIN_IMPACTS", 3)
    R, v, h = np.array([0.003, 0.004]), np.array([5.0, 8.0]), np.full(2, 0.012)
    few = inertia_factors(R, _stone(R), v, h, E, 0.3, 150.0)
    assert few.direct_runs == 2 and not (tmp_path / "cache" / "inertia_table").exists()
    R3, v3, h3 = np.append(R, 0.005), np.append(v, 6.0), np.full(3, 0.012)
    many = inertia_factors(R3, _stone(R3), v3, h3, E, 0.3, 150.0)
    assert many.direct_runs == 0 and len(list((tmp_path / "cache" / "inertia_table").glob("*.npz"))) == 1
