"""studies.targets_study's measurements on small settings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.precompute.hmatrix import compress_bundle
from hailstorm.runtime.storm.scene import Scene, SeatSettings
from studies import targets_study


def test_precompute_cost_measures_a_compressed_build_in_a_child(tmp_path, monkeypatch):
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    seat = dataclasses.replace(SeatSettings.default(), mesh_size=0.02, order=1, load="point")
    cost = targets_study.precompute_cost(1e-2, seat)
    assert cost["wall_s"] > 0 and 0 < cost["peak_GiB"] < 24
    assert 0 < cost["stored_MiB"] < cost["dense_MiB"]


def test_storm_side_by_side_interleaves_after_a_warm_up(seat_bundle, tmp_path, monkeypatch):
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    dense = hailstorm.runtime.load(seat_bundle)
    compressed = hailstorm.runtime.load(compress_bundle(seat_bundle, tmp_path / "h", 1e-2))
    rtf = targets_study.storm_side_by_side(dense, compressed, rounds=2,
                                           scene=Scene.from_flat(duration=0.01, stones=5, seed=1))
    assert set(rtf) == {"dense", "compressed"} and all(len(v) == 2 and np.all(np.array(v) > 0) for v in rtf.values())


def test_dask_same_answer_compares_a_streamed_build_on_a_local_cluster(tmp_path, monkeypatch):
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    seat = dataclasses.replace(SeatSettings.default(), mesh_size=0.02, order=1, load="point")
    same = targets_study.dask_same_answer(1e-2, seat)
    assert 0 <= same["difference"] <= 1e-2 and 0 < same["error_serial"] <= 1e-2 and 0 < same["error_dask"] <= 1e-2


def test_large_surface_reads_the_manifest_and_storms_in_a_child(tmp_path, monkeypatch, seat_bundle):
    from hailstorm.precompute import build_bundle

    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    path = build_bundle(tmp_path / "s", mesh_size=0.02, order=1, load="point", compress_tol=1e-2, stream=True)
    big = targets_study.large_surface(path)
    manifest = hailstorm.runtime.load(path, verify=False).manifest
    assert big["contactable"] == manifest["mesh"]["n_contactable"] > 0
    assert 0 < big["build_peak_GiB"] < 24 and big["error_max"] <= 1e-2
    assert big["storm"]["impacts"] > 0 and big["storm"]["force_N"] > 0 and big["storm"]["reads_hmatrix"] in (True, False)
    assert 0 < big["storm"]["peak_bytes"] / 2**30 < 24
    with pytest.raises(ValueError, match="not a compressed bundle"):
        targets_study.large_surface(seat_bundle)


def test_rows_large_needs_a_bundle(capsys):
    with pytest.raises(SystemExit) as exc:
        targets_study.main(["--rows", "large"])
    assert exc.value.code == 2 and "--rows large needs --large DIR" in capsys.readouterr().err
