"""A compressed bundle read from its H-matrix (``load(..., expand=False)``): the contact API without D's expansion."""

import numpy as np
import pytest

from hailstorm.precompute.hmatrix import compress_bundle
from hailstorm.runtime import capacitance, run_storm, solve_contacts
from hailstorm.runtime.bundle import read
from hailstorm.runtime.bundle.compliance import DenseReader, pair_blocks, reader, response_columns
from hailstorm.runtime.bundle.hreader import HMatrixReader
from hailstorm.runtime.bundle.read import load
from hailstorm.runtime.contact.hertz import press_spheres

#: the two readers evaluate the same float64 H-matrix (products of its factors in other groupings):
#: entries agree to rounding; the contact solves to rounding times the contact compliance's condition
#: number (W of a few contacts on the 15 mm seat: up to ~1e4)
ENTRY_RTOL = 1e-13
SOLVE_RTOL = 1e-9


@pytest.fixture(scope="module")
def seat_h6(seat_bundle, tmp_path_factory):
    """The 15 mm seat compressed to 1e-6: its expansion is float64, the H-matrix's own numbers."""
    return compress_bundle(seat_bundle, tmp_path_factory.mktemp("gfh6") / "seat_h6", 1e-6)


@pytest.fixture(scope="module")
def pair(seat_h6):
    """(read from the H-matrix, read from the expansion) of one compressed bundle."""
    native, dense = load(seat_h6, expand=False), load(seat_h6, expand=True)
    assert native.reads_hmatrix and not dense.reads_hmatrix
    assert isinstance(reader(native), HMatrixReader) and isinstance(reader(dense), DenseReader)
    assert native.hmatrix.ranks.size > 0, "the seat has far blocks stored as factors"
    assert dense.D.dtype == np.float64
    return native, dense


def close(a, b, rtol):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    if b.size == 0:
        return
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(np.abs(b).max(), 1e-300))


def test_entries_and_pairs_are_the_expanded_matrix(pair):
    """HMatrix.entries / pairs / matvec against the expansion (and the compiled kernels against their
    numpy references): unsorted and repeated rows and columns, empty selections."""
    native, dense = pair
    H, D = native.hmatrix, np.asarray(dense.D)
    rng = np.random.default_rng(2)
    rows = np.concatenate([rng.choice(D.shape[0], 40), [0, 0, D.shape[0] - 1]])
    cols = np.concatenate([rng.choice(D.shape[1], 30), [7, 7, D.shape[1] - 1]])
    close(H.entries(rows, cols), D[np.ix_(rows, cols)], ENTRY_RTOL)
    close(H.entries(rows, cols), H.entries_ref(rows, cols), ENTRY_RTOL)  # the compiled kernel and its reference
    assert H.entries(rows, cols).flags.f_contiguous
    x = rng.standard_normal(D.shape[1])
    x[rng.random(D.shape[1]) < 0.5] = 0.0  # zeros are skipped
    close(H.matvec(x), D @ x, ENTRY_RTOL * 10)
    close(H.matvec(x), H.matvec_ref(x), ENTRY_RTOL)
    assert H.entries(rows[:0], cols).shape == (0, cols.size) and H.entries(rows, cols[:0]).shape == (rows.size, 0)
    r, c = rng.choice(D.shape[0], 500), rng.choice(D.shape[1], 500)
    close(H.pairs(r, c), D[r, c], ENTRY_RTOL)
    # what the storm's kernels read entries through, compiled and plain, dense D and H-matrix alike
    import numba

    from hailstorm.runtime.compiled.hblocks import d_entry

    @numba.njit
    def entries(M, r, c):
        out = np.empty(r.size)
        for i in range(r.size):
            out[i] = d_entry(M, r[i], c[i])
        return out

    far = H.blocks[H.blocks[:, 4] >= 0]
    assert np.isin(H.kernel_arrays[4][H.kernel_arrays[1][r], H.kernel_arrays[3][c]],
                   np.flatnonzero(H.blocks[:, 4] >= 0)).any() and far.size, "some entries in far blocks"
    close(entries(H.kernel_arrays, r, c), D[r, c], ENTRY_RTOL)
    np.testing.assert_array_equal(entries(D, r, c), D[r, c])
    close([d_entry(H.kernel_arrays, i, j) for i, j in zip(r[:20], c[:20])], D[r[:20], c[:20]], ENTRY_RTOL)
    assert H.pairs(r[:0], c[:0]).shape == (0,)
    with pytest.raises(ValueError, match="differ in length"):
        H.pairs(r, c[:-1])


def test_the_contact_api_on_the_hmatrix_is_the_expanded_one_and_never_expands(pair):
    """solve_contacts (sticky points: the general path instead of the fused one; frictionless
    unilateral patches with the near field), press_spheres, the incremental capacitance, the
    bundle's own blocks and displacement, and the hat defect's pair blocks: the same numbers
    from the H-matrix as from its expansion, and the H-matrix reader never made the expansion."""
    native, dense = pair
    rng = np.random.default_rng(5)
    tri = np.flatnonzero(dense.contactable[dense.triangles].all(axis=1))
    tri = rng.choice(tri, size=8, replace=False)
    bary = rng.dirichlet(np.ones(3), size=8)
    disp = np.tile([0.0, 0.0, -1e-3], (8, 1)) + 1e-4 * rng.standard_normal((8, 3))
    a, b = (solve_contacts(gf, tri, bary, disp) for gf in (native, dense))
    close(a.forces, b.forces, SOLVE_RTOL)
    close(a.surface_displacement, b.surface_displacement, SOLVE_RTOL)
    rows = np.array([3, 1, 3, 40])
    kw = dict(mode="frictionless", unilateral=True, patch_radius=np.full(8, 4e-3), near_field="auto", rows=rows)
    a, b = (solve_contacts(gf, tri, bary, disp, **kw) for gf in (native, dense))
    close(a.forces, b.forces, SOLVE_RTOL)
    close(a.surface_displacement, b.surface_displacement, SOLVE_RTOL)
    assert a.active.tolist() == b.active.tolist()
    a, b = (press_spheres(gf, tri[:4], bary[:4], np.full(4, 1.5e-3), 5e-3) for gf in (native, dense))
    close(a.normal_force, b.normal_force, SOLVE_RTOL)
    close(a.patch_radius, b.patch_radius, SOLVE_RTOL)
    close(a.solution.surface_displacement, b.solution.surface_displacement, SOLVE_RTOL)
    caps = [capacitance(gf, tri[:5], bary[:5]) for gf in (native, dense)]
    for cap in caps:
        cap.add(int(tri[6]), bary[6])
        cap.remove(1)
    f = [cap.forces(disp[:5]) for cap in caps]
    close(f[0], f[1], SOLVE_RTOL)
    close(caps[0].surface_displacement(f[0]), caps[1].surface_displacement(f[1]), SOLVE_RTOL)
    close(caps[0].surface_response(rows), caps[1].surface_response(rows), ENTRY_RTOL)
    V = np.flatnonzero(dense.contactable)[:9]
    close(native.compliance(rows, V), dense.compliance(rows, V), ENTRY_RTOL)
    close(native.displacement(V[:3], np.ones((3, 3))), dense.displacement(V[:3], np.ones((3, 3))), ENTRY_RTOL)
    close(pair_blocks(native, rows, V[:4]), pair_blocks(dense, rows, V[:4]), ENTRY_RTOL)
    cols = np.concatenate([3 * dense.column_of[V[:3], None] + np.arange(3), [[-1, -1, -1]]]).ravel()
    loc, w = np.array([[0, 1, 3], [2, 3, 0]]), np.array([[0.5, 0.5, 0.0], [0.7, 0.3, 0.0]])
    close(response_columns(native, cols, loc, w), response_columns(dense, cols, loc, w), ENTRY_RTOL)
    assert not native.expanded


def test_load_reads_a_large_compressed_bundle_from_its_hmatrix(seat_h6, seat_bundle, monkeypatch):
    """expand=None: the H-matrix when the expansion would exceed EXPAND_UP_TO, else the expansion;
    a dense bundle has no H-matrix to read; expand must be a bool or None."""
    assert not load(seat_h6).reads_hmatrix  # 1.5 MiB: expanded
    assert not getattr(load(seat_bundle), "reads_hmatrix", False)
    monkeypatch.setattr(read, "EXPAND_UP_TO", 1 << 10)
    gf = load(seat_h6)
    assert gf.reads_hmatrix and isinstance(reader(gf), HMatrixReader)
    with pytest.raises(ValueError, match="expand must be"):
        load(seat_h6, expand="no")


def test_a_storm_reading_the_hmatrix_is_the_expanded_storm(pair):
    """The storm's kernels read D's entries from the H-matrix (d_entry) and its displacements
    through the reader: the same impacts, forces, stone paths and frames as on the float64
    expansion (the entries agree to rounding: 1e-9 of the largest), and D never expanded."""
    from hailstorm.runtime.storm.scene import Scene

    native, dense = pair
    scene = Scene.from_flat(duration=0.03, stones=20, seed=3)
    a = run_storm(native, scene, progress=False, keep_frames=True)
    b = run_storm(dense, scene, progress=False, keep_frames=True)
    assert a.stats.impacts == b.stats.impacts > 0
    assert a.stats.max_contact_force == pytest.approx(b.stats.max_contact_force, rel=1e-9)
    assert a.stats.max_indentation_m == pytest.approx(b.stats.max_indentation_m, rel=1e-9)
    close(a.history[:, 1], b.history[:, 1], 1e-9)
    assert len(a.frames) == len(b.frames) > 0
    for fa, fb in zip(a.frames, b.frames):
        close(fa.positions, fb.positions, 1e-9)
        close(fa.displacement, fb.displacement, 1e-6)  # frames are float32
    assert not native.expanded
