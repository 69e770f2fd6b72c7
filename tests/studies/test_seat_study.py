"""The seat study's command line (its functions are tested in tests/precompute/test_saddle.py)."""

from __future__ import annotations

from studies.seat_study import main


def test_main_writes_its_output_with_the_command(tmp_path, capsys):
    out = tmp_path / "seat.txt"
    assert main(["--mesh-size", "0.02", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    lines = out.read_text().splitlines()
    assert lines[0] == "$ python -m studies.seat_study --mesh-size 0.02"
    assert lines[1].startswith("# ") and lines[-1].startswith("# wall time")
    for site in ("rear", "middle", "nose"):
        assert any(line.startswith(site) for line in lines) and site in printed
