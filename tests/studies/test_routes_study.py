"""studies.routes_study on coarse seats: the rows it reports are the bundles' own figures."""

from __future__ import annotations

import numpy as np
import pytest

from studies import routes_study


def test_route_rows_on_coarse_seats(tmp_path, monkeypatch):
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    rows = routes_study.route_rows([0.02, 0.015], tol=1e-2, duration=0.01, repeat=1)
    assert [(r["size_mm"], r["storage"]) for r in rows] == [(20.0, "dense"), (20.0, "H 0.01"),
                                                            (15.0, "dense"), (15.0, "H 0.01")]
    dense20, h20, ref, h15 = rows
    assert ref["err"] is None  # the reference
    # the compressed D stores less and reads as the dense one: the same errors to the compression's tol
    for d, h in ((dense20, h20), (ref, h15)):
        assert h["stored_MiB"] < d["stored_MiB"] and h["col_err"] <= 1e-2
        assert h["precompute_s"] == d["precompute_s"] > 0 and h["compress_s"] > 0
    assert h15["err"]["max"] <= 2e-2  # against its own dense source
    assert abs(h20["err"]["max"] - dense20["err"]["max"]) <= 2e-2
    assert 0 <= dense20["err"]["median"] <= dense20["err"]["max"] and dense20["err"]["small"] <= dense20["err"]["max"]
    for r in rows:
        assert len(r["solve_ms"]) == 20 and all(np.isfinite(r["solve_ms"])) and len(r["rtf"]) == 1
    table = routes_study.format_rows(rows)
    assert len(table) == 2 + len(rows) and "| 15 | dense | " in table[4] and "reference" in table[4]


def test_plot_frontier_draws_the_rows(tmp_path):
    """The chart from rows shaped as route_rows gives them (the reference left out); a table with
    no error to draw is refused."""
    def row(size, storage, err, pre, comp, mib):
        return {"size_mm": size, "storage": storage, "err": err, "precompute_s": pre, "compress_s": comp,
                "stored_MiB": mib, "solve_ms": [4.0, 5.0, 6.0], "rtf": [0.4]}

    e = {"max": 0.039, "median": 0.004, "small": 0.029}
    rows = [row(6, "dense", e, 9.0, 0.0, 107.8), row(6, "H 0.01", e, 9.0, 3.4, 22.9),
            row(3, "dense", None, 69.7, 0.0, 1089.2)]
    out = routes_study.plot_frontier(rows, tmp_path / "sub" / "frontier.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    assert list(out.parent.iterdir()) == [out]  # written in place of a temporary, nothing left over
    with pytest.raises(ValueError, match="needs a row"):
        routes_study.plot_frontier(rows[2:], tmp_path / "none.png")


def test_notebook_executes_on_small_settings(run_notebook):
    """``notebooks/routes_frontier.ipynb`` on coarse seats: it prints the table and draws the chart,
    and leaves the committed chart alone."""
    from pathlib import Path

    png = Path(__file__).resolve().parents[2] / "notebooks" / "figures" / "routes_frontier.png"
    before = png.stat().st_mtime_ns if png.exists() else None
    text = run_notebook("routes_frontier.ipynb")
    assert "SMALL = True" in text and "| 20 | dense |" in text and "| 15 | dense |" in text
    assert "chart: routes_frontier_small.png" in text
    assert (png.stat().st_mtime_ns if png.exists() else None) == before
