"""Atomic writes: the old file survives a failed write, and nothing is left behind."""

import numpy as np
import pytest

from hailstorm.runtime.bundle.atomic import replacing, write_text_atomic


def test_write_text_atomic_replaces(tmp_path):
    p = tmp_path / "a.json"
    p.write_text("old")
    assert write_text_atomic(p, "new") == p
    assert p.read_text() == "new"
    assert [x.name for x in tmp_path.iterdir()] == ["a.json"]


def test_failed_write_keeps_the_old_file(tmp_path):
    p = tmp_path / "ref.npz"
    np.savez(p, u=np.arange(3))
    with pytest.raises(RuntimeError):
        with replacing(p) as tmp:
            np.savez(tmp, u=np.zeros(5))  # the writer keeps the suffix: no ".npz.npz"
            assert tmp.suffix == ".npz" and tmp.stat().st_size > 0
            raise RuntimeError("interrupted")
    assert np.array_equal(np.load(p)["u"], np.arange(3))
    assert [x.name for x in tmp_path.iterdir()] == ["ref.npz"]


def test_permissions_are_those_of_a_plain_write(tmp_path):
    """A new file gets 0o666 minus the umask (not mkstemp's private 0o600); a replaced
    file keeps its mode."""
    import os
    import stat

    umask = os.umask(0o022)
    try:
        new = write_text_atomic(tmp_path / "new.json", "{}")
        assert stat.S_IMODE(new.stat().st_mode) == 0o644
        old = tmp_path / "old.json"
        old.write_text("x")
        old.chmod(0o640)
        write_text_atomic(old, "y")
        assert stat.S_IMODE(old.stat().st_mode) == 0o640 and old.read_text() == "y"
    finally:
        os.umask(umask)
