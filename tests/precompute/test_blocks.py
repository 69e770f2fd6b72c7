"""Streaming D to disk in column blocks: resume after an interruption, refuse stale blocks, full disks."""

import errno
import json
import logging
import os

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.precompute import build_bundle
from hailstorm.precompute.blocks import work_dir
from hailstorm.precompute.greens import column_blocks
from hailstorm.runtime.bundle.format import BundleError, array_hash
from helpers import count_solves, interrupt_after

#: small blocks, so that the 216-node box has several (its D is 648 x 375 columns... of 8 bytes)
BLOCK = 40_000


def _same(a, b, rtol=1e-12):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and np.abs(a - b).max() <= rtol * np.abs(b).max()


def _interrupted_build(out, mesh, monkeypatch, blocks=3):
    """A streamed build of ``mesh`` to ``out`` stopped (KeyboardInterrupt) after ``blocks`` blocks:
    the indices of the blocks written."""
    with monkeypatch.context() as m:
        written = interrupt_after(m, blocks)
        with pytest.raises(KeyboardInterrupt):
            build_bundle(out, mesh=mesh, young=1e6, poisson=0.3, block_bytes=BLOCK)
    return written


def test_blocks_cover_the_columns_in_batches():
    blocks = column_blocks(1000, 1000, block_bytes=8 * 1000 * 100, batch=32)
    assert blocks[0] == (0, 96) and blocks[-1][1] == 1000
    assert all(a[1] == b[0] for a, b in zip(blocks, blocks[1:]))
    assert column_blocks(10, 5, block_bytes=1) == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]


def test_streamed_bundle_equals_in_memory_D_and_its_hash(tmp_path, small_box, box_bundle):
    out = build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK)
    gf = hailstorm.runtime.load(out, rehash=True)
    ref = hailstorm.runtime.load(box_bundle)  # one block, the same inputs
    assert _same(gf.D, ref.D)  # blocks batch the right-hand sides differently: rounding only
    assert gf.manifest["arrays"]["compliance"]["sha256"] == array_hash(np.load(out / "compliance.npy"))
    assert gf.manifest["solve_stats"]["blocks"] > 3
    assert not work_dir(out).exists()  # the work directory went with the finished bundle


def test_interrupted_run_resumes_computing_only_the_missing_blocks(tmp_path, small_box, monkeypatch, caplog):
    out = tmp_path / "b"
    written = _interrupted_build(out, small_box, monkeypatch)
    assert written == [0, 1, 2] and not out.exists()
    assert len(list((work_dir(out) / "blocks").iterdir())) == 3
    calls = count_solves(monkeypatch)
    with caplog.at_level(logging.INFO):
        build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK)
    n = hailstorm.runtime.load(out).manifest["solve_stats"]["blocks"]
    assert f"resuming: 3 of {n} blocks done" in caplog.text
    assert len(calls) == n - 3 and calls[0][0] > 0  # the first three were not solved again
    fresh = build_bundle(tmp_path / "fresh", mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK)
    assert np.array_equal(np.asarray(hailstorm.runtime.load(out).D), np.asarray(hailstorm.runtime.load(fresh).D))


def test_blocks_of_another_material_are_never_used(tmp_path, small_box, monkeypatch, caplog):
    out = tmp_path / "b"
    _interrupted_build(out, small_box, monkeypatch)
    calls = count_solves(monkeypatch)
    with caplog.at_level(logging.INFO):
        gf = hailstorm.runtime.load(build_bundle(out, mesh=small_box, young=2e6, poisson=0.3, block_bytes=BLOCK))
    assert "starting afresh" in caplog.text and "resuming" not in caplog.text
    assert len(calls) == gf.manifest["solve_stats"]["blocks"]
    ref = hailstorm.runtime.load(build_bundle(tmp_path / "ref", mesh=small_box, young=2e6, poisson=0.3))
    assert _same(gf.D, ref.D)


def test_a_block_tagged_with_another_key_or_damaged_is_computed_again(tmp_path, small_box, monkeypatch, caplog):
    out = tmp_path / "b"
    _interrupted_build(out, small_box, monkeypatch)
    work = work_dir(out)
    rec = work / "blocks" / "000001.json"
    r = json.loads(rec.read_text())
    rec.write_text(json.dumps({**r, "key": "0" * 64}))  # a block of other inputs
    meta = json.loads((work / "work.json").read_text())
    rows = meta["shape"][0]
    with open(work / "compliance.npy", "r+b") as fh:  # flip a byte of block 2
        np.lib.format.read_array_header_1_0(fh) if np.lib.format.read_magic(fh) == (1, 0) else None
        header = fh.tell()
        start = meta["blocks"][2][0]
        fh.seek(header + 8 * rows * start + 5)
        b = fh.read(1)
        fh.seek(-1, os.SEEK_CUR)
        fh.write(bytes([b[0] ^ 0xFF]))
    calls = count_solves(monkeypatch)
    with caplog.at_level(logging.INFO):
        gf = hailstorm.runtime.load(build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK))
    assert "another cache key" in caplog.text and "do not match" in caplog.text
    n = gf.manifest["solve_stats"]["blocks"]
    assert f"resuming: 1 of {n} blocks done" in caplog.text and len(calls) == n - 1
    ref = hailstorm.runtime.load(build_bundle(tmp_path / "ref", mesh=small_box, young=1e6, poisson=0.3))
    assert _same(gf.D, ref.D)


def test_full_disk_is_a_clear_error_and_keeps_finished_blocks(tmp_path, small_box, monkeypatch):
    out = tmp_path / "b"
    real = os.pwrite
    count = [0]

    def pwrite(fd, data, offset):
        if not os.readlink(f"/proc/self/fd/{fd}").endswith("compliance.npy"):
            return real(fd, data, offset)  # the lock file's pid
        count[0] += 1
        if count[0] > 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, data, offset)

    with monkeypatch.context() as m:
        m.setattr(os, "pwrite", pwrite)
        with pytest.raises(BundleError, match="No space left on device.*2 of .* finished blocks are kept"):
            build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK)
    assert not out.exists()
    calls = count_solves(monkeypatch)
    gf = hailstorm.runtime.load(build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK))
    assert len(calls) == gf.manifest["solve_stats"]["blocks"] - 2


def test_full_disk_from_the_cli_is_one_line_and_exit_3(tmp_path, monkeypatch, capsys):
    from hailstorm.cli import main

    real = os.pwrite

    def pwrite(fd, data, offset):
        if not os.readlink(f"/proc/self/fd/{fd}").endswith("compliance.npy"):
            return real(fd, data, offset)  # the lock file's pid
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "pwrite", pwrite)
    rc = main(["precompute", "--mesh-size", "0.03", "--order", "1", "--out", str(tmp_path / "b"), "-q"])
    err = capsys.readouterr().err
    assert rc == 3
    assert err.count("\n") == 1 and "No space left on device" in err and "Traceback" not in err


def test_too_little_disk_is_refused_before_solving(tmp_path, small_box, monkeypatch):
    import shutil

    import hailstorm.precompute.resources as resources

    calls = count_solves(monkeypatch)
    monkeypatch.setattr(resources.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**9, 10**9, 1000))
    with pytest.raises(resources.TooLargeError, match="of disk for D"):
        build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3)
    assert calls == []


def test_interrupted_while_writing_the_bundle_keeps_D_and_solves_nothing_again(tmp_path, small_box, monkeypatch,
                                                                                caplog):
    import hailstorm.runtime.bundle.write as bundle

    out = tmp_path / "b"
    real = bundle.manifest_hash
    with monkeypatch.context() as m:
        def fail(manifest):  # after D moved into the bundle's temporary, before the manifest
            raise KeyboardInterrupt

        m.setattr(bundle, "manifest_hash", fail)
        with pytest.raises(KeyboardInterrupt):
            build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK)
    assert not out.exists() and (work_dir(out) / "compliance.npy").is_file()  # D moved back to the work directory
    assert bundle.manifest_hash is real
    calls = count_solves(monkeypatch)
    with caplog.at_level(logging.INFO):
        gf = hailstorm.runtime.load(build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK))
    n = gf.manifest["solve_stats"]["blocks"]
    assert f"resuming: {n} of {n} blocks done" in caplog.text and calls == []


def test_the_streamed_D_is_not_read_again_on_load(tmp_path, small_box, monkeypatch):
    import hailstorm.runtime.bundle.format as bundle_format

    out = build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK)
    scanned = []
    real = bundle_format.scan_array
    monkeypatch.setattr(bundle_format, "scan_array", lambda a: scanned.append(a.shape) or real(a))
    gf = hailstorm.runtime.load(out)
    assert gf.D.shape not in scanned  # its hash came from its bytes on disk when it was written
    hailstorm.runtime.load(out, rehash=True)
    assert gf.D.shape in scanned  # and a rehash still reads it
