"""studies.coarsening_study on small settings."""

from __future__ import annotations

import numpy as np

from studies import coarsening_study


def test_coarsening_rows_count_the_factor_and_the_compliance():
    plain, coarse = (coarsening_study.coarsening_row(0.003, c) for c in (2.5, 10))
    # at 3 mm the pad (12-15 mm) is only a few elements thick either way: fewer vertices, about the same
    # factor (2.54 M and 2.59 M entries); at 2 mm C = 10 cuts it 6 %, more at finer sizes (docs/scale.md)
    assert coarse["points"] < plain["points"], (plain, coarse)
    assert 0.5 < coarse["nnz_L"] / plain["nnz_L"] < 1.1 and coarse["factor_s"] > 0
    # a pad of 12-15 mm under 4 mm Gaussian loads of 1 N: ~16 um/N (P1 at 3 mm), within 10 % of each
    # other (the meshes differ; measured +0.3 / +3.2 / +0.4 %)
    for r in (plain, coarse):
        assert np.all((np.array(r["compliance"]) > 5e-6) & (np.array(r["compliance"]) < 1e-4)), r["compliance"]
    assert np.allclose(coarse["compliance"], plain["compliance"], rtol=0.1)


def test_main_prints_a_row_per_coarsening(capsys, tmp_path):
    out = tmp_path / "c.txt"
    assert coarsening_study.main(["--mesh-size", "0.012", "--coarsenings", "2.5,4", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows = [line for line in text.splitlines() if line.startswith("| 2.5 ") or line.startswith("| 4 ")]
    assert len(rows) == 2 and "+0.0 %" in rows[0]
    assert out.read_text().startswith("$ python -m studies.coarsening_study --mesh-size 0.012")
