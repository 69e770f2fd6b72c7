"""The numpy-only VTU writer and reader against meshio (an independent implementation of the format)."""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime.output.vtu import read_vtu, write_vtu

meshio = pytest.importorskip("meshio")


def _grid(n: int = 5000, seed: int = 0):
    rng = np.random.default_rng(seed)
    X = rng.random((n, 3))
    tri = rng.integers(0, n, (2 * n, 3))
    u = rng.standard_normal((n, 3))
    return X, tri, u


def test_meshio_reads_what_the_writer_wrote_bit_for_bit(tmp_path):
    X, tri, u = _grid(20000)  # over 32 KiB per array: several zlib blocks
    ids = np.arange(len(X), dtype=np.int64) - 7
    write_vtu(tmp_path / "a.vtu", X, "triangle", tri, {"displacement": u, "|u|": np.linalg.norm(u, axis=1), "id": ids})
    m = meshio.read(tmp_path / "a.vtu")
    assert np.array_equal(m.points, X)
    assert np.array_equal(m.cells_dict["triangle"], tri)
    assert np.array_equal(m.point_data["displacement"], u)
    assert np.array_equal(m.point_data["|u|"], np.linalg.norm(u, axis=1))
    assert np.array_equal(m.point_data["id"], ids)


def test_vertex_cells_round_trip_through_meshio(tmp_path):
    pos = np.array([[0.0, 0.1, 0.2], [1.0, 1.1, 1.2]])
    write_vtu(tmp_path / "s.vtu", pos, "vertex", np.arange(2)[:, None],
              {"radius": np.array([0.01, 0.02]), "force": np.zeros((2, 3))})
    m = meshio.read(tmp_path / "s.vtu")
    assert np.array_equal(m.cells_dict["vertex"].ravel(), [0, 1])
    assert np.array_equal(m.point_data["radius"], [0.01, 0.02])
    points, data = read_vtu(tmp_path / "s.vtu")
    assert np.array_equal(points, pos) and np.array_equal(data["force"], np.zeros((2, 3)))


@pytest.mark.parametrize("binary, compression", [(True, "zlib"), (True, None), (False, None)])
def test_the_reader_reads_meshios_files(tmp_path, binary, compression):
    X, tri, u = _grid()
    ids = np.arange(len(X), dtype=np.int64)
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(X, [("triangle", tri)], point_data={"displacement": u, "id": ids}),
                 binary=binary, compression=compression)
    points, data = read_vtu(tmp_path / "m.vtu")
    # binary: bit for bit; ascii: meshio prints 12 significant digits ("{:.11e}"), so 1e-11 relative
    rtol = 0.0 if binary else 1e-11
    np.testing.assert_allclose(points, X, rtol=rtol, atol=0)
    np.testing.assert_allclose(data["displacement"], u, rtol=rtol, atol=0)
    assert np.array_equal(data["id"], ids)


def test_point_data_of_the_wrong_length_is_refused(tmp_path):
    X, tri, u = _grid(10)
    with pytest.raises(ValueError, match="point data 'u' has 9 rows for 10 points"):
        write_vtu(tmp_path / "a.vtu", X, "triangle", tri, {"u": u[:9]})
