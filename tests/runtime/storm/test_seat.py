"""The seat's state on its own (:class:`SeatState`): the displacement it tracks, its bound,
its peaks and the memory it holds, against the bundle's D applied by hand.

The contact sets are made here (hand-made weights on the synthetic plate's vertices, not
the storm's :class:`ContactSet`): what the seat needs of a set is ``stones``, ``G``, ``cols``
and ``DVV`` (:class:`hailstorm.runtime.storm.seat.LoadedSet`). The oracle assembles the
vertex forces of the contacts and multiplies the bundle's D by them (``D`` maps the
contactable dofs, through ``column_of``, to the displacement of every surface dof).
"""

from __future__ import annotations

import gc
import tracemalloc
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import plate_gf

from hailstorm.runtime.storm.seat import SeatState

N = 13  # the plate's grid: vertex (i, j) is i * N + j, the ring i or j in {0, 12} clamped

#: contacts: (stone id, vertices, weights summing to 1, unit normal)
CONTACTS = (
    (4, np.array([3 * N + 3, 3 * N + 4, 4 * N + 3]), np.array([0.5, 0.3, 0.2]), np.array([0.0, 0.0, 1.0])),
    (9, np.array([8 * N + 8, 8 * N + 9, 9 * N + 8, 9 * N + 9]), np.array([0.1, 0.2, 0.3, 0.4]),
     np.array([0.6, 0.0, 0.8])),
    (2, np.array([9 * N + 2]), np.array([1.0]), np.array([0.0, -0.6, 0.8])),
)


@pytest.fixture(scope="module")
def gf():
    return plate_gf(N)


def loaded_set(gf, contacts, sticky=False):
    """A :class:`LoadedSet` of ``contacts``: the union V of their vertices, the D columns of V,
    ``G`` (vertex forces on those columns per unit multiplier) and ``DVV = D[V, cols] G``."""
    m = 3 if sticky else 1
    V = np.unique(np.concatenate([c[1] for c in contacts]))
    assert np.all(gf.column_of[V] >= 0)
    cols = (3 * gf.column_of[V][:, None] + np.arange(3)).ravel()
    rows = (3 * V[:, None] + np.arange(3)).ravel()
    G = np.zeros((cols.size, m * len(contacts)))
    for k, (_, verts, w, n) in enumerate(contacts):
        at = np.searchsorted(V, verts)
        for d in range(3):
            if sticky:
                G[3 * at + d, 3 * k + d] = w
            else:
                G[3 * at + d, k] = w * n[d]
    return SimpleNamespace(stones=np.array([c[0] for c in contacts]), G=G, cols=cols,
                           DVV=np.asarray(gf.D)[np.ix_(rows, cols)] @ G, V=V)


def hand_field(gf, contacts, lam, sticky=False):
    """Displacement (n, 3) of the surface under the contacts' multipliers ``lam``: the vertex
    forces assembled contact by contact, then D times the forces of the contactable dofs."""
    n = gf.vertices.shape[0]
    F = np.zeros((n, 3))
    for k, (_, verts, w, nrm) in enumerate(contacts):
        f = lam[3 * k:3 * k + 3] if sticky else lam[k] * nrm
        F[verts] += w[:, None] * f[None, :]
    f_cols = np.zeros(gf.D.shape[1])
    live = np.flatnonzero(gf.column_of >= 0)
    for d in range(3):
        f_cols[3 * gf.column_of[live] + d] = F[live, d]
    return (np.asarray(gf.D) @ f_cols).reshape(n, 3)


def _norms(u):
    return np.sqrt((u * u).sum(axis=1))


#: the plate's displacements are ~1e-5 m per N; the products are sums of a few hundred terms
ATOL = 1e-18


@pytest.mark.parametrize("sticky", [False, True])
def test_displacement_is_D_times_the_forces_by_hand(gf, sticky):
    seat = SeatState(gf)
    cc = loaded_set(gf, CONTACTS, sticky)
    rng = np.random.default_rng(3)
    lam = rng.uniform(-2.0, -0.5, len(CONTACTS) * (3 if sticky else 1))
    seat.set_forces(cc, lam)
    u = hand_field(gf, CONTACTS, lam, sticky)
    assert seat.loaded and np.abs(u).max() > 1e-6
    np.testing.assert_allclose(seat.u, u, rtol=1e-12, atol=ATOL)
    verts = np.array([0, 3 * N + 3, 8 * N + 9, 100, 9 * N + 2, 50])  # a clamped one, loaded ones, others
    np.testing.assert_allclose(seat.u_at(verts), u[verts], rtol=1e-12, atol=ATOL)
    assert seat.u_at(np.zeros(0, dtype=np.intp)).shape == (0, 3)
    # the bound: 1.5 x the largest |u| at the loaded vertices
    bound = 1.5 * _norms(u[cc.V]).max()
    assert seat.umax == pytest.approx(bound, rel=1e-12)
    assert seat.umax_seen == seat.umax_step == seat.umax
    # what the compiled queries get: the same load
    loaded, cols, forces = seat.kernel_load()
    assert loaded
    np.testing.assert_allclose((np.asarray(gf.D)[:, cols] @ forces).reshape(-1, 3), u, rtol=1e-12, atol=ATOL)
    # new forces: the displacement follows (the cached field is not served stale)
    seat.set_forces(cc, 3.0 * lam)
    np.testing.assert_allclose(seat.u, 3.0 * u, rtol=1e-12, atol=ATOL)
    assert seat.umax == pytest.approx(3.0 * bound, rel=1e-12)
    seat.end_step()
    seat.set_forces(cc, 0.5 * lam)
    assert seat.umax == pytest.approx(0.5 * bound, rel=1e-12)
    assert seat.umax_step == pytest.approx(3.0 * bound, rel=1e-12)  # the step's largest, until end_step
    assert seat.umax_seen == pytest.approx(3.0 * bound, rel=1e-12)
    seat.end_step()
    assert seat.umax_step == seat.umax


def test_empty_set_unloads_the_seat(gf):
    seat = SeatState(gf)
    n = gf.vertices.shape[0]

    def unloaded():
        assert not seat.loaded and seat.umax == 0.0
        np.testing.assert_array_equal(seat.u, np.zeros((n, 3)))
        np.testing.assert_array_equal(seat.u_at(np.array([5, 60, 100])), np.zeros((3, 3)))
        loaded, cols, forces = seat.kernel_load()
        assert not loaded and cols.size == 0 and forces.size == 0 and cols.dtype == np.int64

    unloaded()  # a new seat
    np.testing.assert_array_equal(seat.peak_field(), np.zeros((n, 3)))
    cc = loaded_set(gf, CONTACTS)
    lam = np.array([-1.0, -2.0, -0.5])
    for release in (lambda: seat.set_forces(None, np.zeros(0)),  # no set
                    lambda: seat.set_forces(cc, np.zeros(3)),  # a set without force
                    lambda: seat.set_forces(loaded_set(gf, CONTACTS[:1]), np.zeros(0))):
        seat.set_forces(cc, lam)
        assert seat.loaded and seat.umax > 0.0
        seen = seat.umax_seen
        release()
        unloaded()
        assert seat.umax_seen == seen  # the largest seen stays
    # an unloaded seat's peak field holds what was loaded since the last call; the next is empty
    want = _brute_peak(gf, [(CONTACTS, lam, False)], np.zeros((n, 3)))
    assert np.abs(want).max() > 0.0
    np.testing.assert_allclose(seat.peak_field(), want, rtol=1e-12, atol=ATOL)
    np.testing.assert_array_equal(seat.peak_field(), np.zeros((n, 3)))


def _brute_peak(gf, history, u_now):
    """Per vertex, the largest of ``u_now`` and each stone's own field at its deepest dent:
    ``history`` lists (contacts of the set, multipliers, sticky); a stone's dent at an instant is
    the largest |displacement| its own load causes at the set's loaded vertices."""
    best = {}  # stone -> (dent, field)
    for contacts, lam, sticky in history:
        m = 3 if sticky else 1
        V = np.unique(np.concatenate([c[1] for c in contacts]))
        for k, c in enumerate(contacts):
            own = np.zeros(m * len(contacts))
            own[m * k:m * k + m] = lam[m * k:m * k + m]
            field = hand_field(gf, contacts, own, sticky)
            dent = _norms(field[V]).max()
            if dent > 0 and (c[0] not in best or dent > best[c[0]][0]):
                best[c[0]] = (dent, field)
    fields = np.stack([u_now] + [f for _, f in best.values()])
    pick = np.argmax((fields * fields).sum(axis=2), axis=0)
    return fields[pick, np.arange(u_now.shape[0])]


@pytest.mark.parametrize("sticky", [False, True])
def test_peak_field_is_the_brute_force_peak_over_a_sequence(gf, sticky):
    """Impacts one after another (a stone alone in its set, its force rising and falling, then
    released; another set; two stones together) and a contact released within a sub-step
    (``peak`` given, no force left): per vertex, the peak field is the largest over the sequence,
    computed by hand from each instant's forces."""
    m = 3 if sticky else 1
    rng = np.random.default_rng(7)
    d = np.array([0.2, -0.3, -1.0])  # a sticky contact's force direction

    def lam_of(scales):
        return np.concatenate([s * d for s in scales]) if sticky else -np.asarray(scales, dtype=float)

    seat = SeatState(gf)
    history = []
    sets = [CONTACTS[:1], CONTACTS[1:2], CONTACTS[1:], CONTACTS]
    for contacts in sets:
        cc = loaded_set(gf, contacts, sticky)
        s = len(contacts)
        for level in (0.2, 0.9, 1.7, 1.1, 0.3):  # an impact: the force rises and falls
            lam = lam_of(level * rng.uniform(0.5, 1.5, s))
            seat.set_forces(cc, lam)
            history.append((contacts, lam, sticky))
        seat.set_forces(None, np.zeros(0))
    # released within the sub-step: no force left, its peak still counts
    cc = loaded_set(gf, CONTACTS[2:], sticky)
    peak = lam_of([2.5])
    seat.set_forces(cc, np.zeros(m), peak)
    history.append((CONTACTS[2:], peak, sticky))
    assert not seat.loaded
    # and a light load left on at the frame
    cc = loaded_set(gf, CONTACTS[:2], sticky)
    lam = lam_of([0.05, 0.02])
    seat.set_forces(cc, lam)
    history.append((CONTACTS[:2], lam, sticky))
    u_now = hand_field(gf, CONTACTS[:2], lam, sticky)
    want = _brute_peak(gf, history, u_now)
    got = seat.peak_field()
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=ATOL)
    # for one stone at a time (fixed weights) it is the per-vertex maximum over time of |u|
    times = [hand_field(gf, c, la, sticky) for c, la, _ in history] + [u_now]
    one_at_a_time = np.max([_norms(u) for u in times], axis=0)
    assert _norms(got).max() == pytest.approx(one_at_a_time.max(), rel=1e-12)
    # a new interval: only the current displacement
    np.testing.assert_allclose(seat.peak_field(), u_now, rtol=1e-12, atol=ATOL)


def test_peak_follows_the_deepest_dent_not_the_largest_force(gf):
    """A contact re-weighted within a frame (its patch widened: more force, a shallower dent) keeps
    the field of its deepest dent, by hand: the narrow one's."""
    c = N * 6 + 6
    ring = np.array([c - N - 1, c - N, c - N + 1, c - 1, c, c + 1, c + N - 1, c + N, c + N + 1])
    narrow = ((1, np.array([c]), np.array([1.0]), np.array([0.0, 0.0, 1.0])),)
    wide = ((1, ring, np.full(9, 1.0 / 9.0), np.array([0.0, 0.0, 1.0])),)
    seat = SeatState(gf)
    seat.set_forces(loaded_set(gf, narrow), np.array([-1.0]))
    seat.set_forces(loaded_set(gf, wide), np.array([-2.0]))
    seat.set_forces(None, np.zeros(0))
    u_narrow, u_wide = hand_field(gf, narrow, np.array([-1.0])), hand_field(gf, wide, np.array([-2.0]))
    assert _norms(u_narrow).max() > _norms(u_wide).max()  # the premise: the narrow dent is deeper
    assert np.any(_norms(u_wide) > _norms(u_narrow))  # ... though not everywhere
    np.testing.assert_allclose(seat.peak_field(), u_narrow, rtol=1e-12, atol=ATOL)


def _held_bytes(run, calls):
    gc.collect()
    tracemalloc.start()
    try:
        run(calls)
        gc.collect()
        return tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_the_calls(gf):
    """The seat holds one load, one cached field and one peak per stone: the memory allocated
    (and still held) over 200 and over 2000 calls of set_forces / u / u_at / end_step (without
    a frame in between) is the same within 16 KiB, where keeping one call's forces (54
    float64, ~0.5 KiB with the array's header) would add ~0.9 MiB over the extra 1800 calls."""
    cc = loaded_set(gf, CONTACTS)
    ring = np.arange(2 * N + 2, 2 * N + 12)
    big = ((5, ring, np.full(ring.size, 0.1), np.array([0.0, 0.0, 1.0])),) + CONTACTS
    cc2 = loaded_set(gf, big)
    assert cc2.cols.size == 54
    lam = np.array([-1.0, -2.0, -0.5])
    lam2 = np.array([-1.5, -1.0, -2.0, -0.5])
    probe = np.array([10, 20, 30])

    def run(calls, seat=SeatState(gf)):
        for i in range(calls):
            if i % 2:
                seat.set_forces(cc, lam * (1.0 + (i % 7)))
            else:
                seat.set_forces(cc2, lam2 * (1.0 + (i % 5)), lam2 * 9.0)
            seat.u_at(probe)
            if i % 10 == 0:
                seat.u  # noqa: B018 (the cached field)
                seat.end_step()

    run(50)  # warm: the seat's one-off state exists
    few, many = _held_bytes(run, 200), _held_bytes(run, 2000)
    assert abs(many - few) < 16 * 1024, (few, many)


def test_row_major_memmap_is_held_column_major(gf, tmp_path):
    """A bundle whose D is a row-major memmap: the seat holds a column-major copy, same values."""
    path = tmp_path / "D.npy"
    np.save(path, np.ascontiguousarray(gf.D))
    D = np.load(path, mmap_mode="r")
    assert isinstance(D, np.memmap) and D.flags.c_contiguous
    src = SimpleNamespace(D=D, column_of=gf.column_of, vertices=gf.vertices)
    seat = SeatState(src)
    assert seat.D.flags.f_contiguous and not isinstance(seat.D, np.memmap)
    np.testing.assert_array_equal(seat.D, gf.D)
    lam = np.array([-1.0, -2.0, -0.5])
    seat.set_forces(loaded_set(gf, CONTACTS), lam)
    np.testing.assert_allclose(seat.u, hand_field(gf, CONTACTS, lam), rtol=1e-12, atol=ATOL)


def test_on_a_bundle_from_disk(box_bundle):
    """A bundle as loaded from disk (the FEM box; D a column-major memmap): held without a copy,
    and the displacement of contacts on its top is D times their forces by hand."""
    from hailstorm.runtime.bundle.read import load

    gf = load(box_bundle)
    assert isinstance(gf.D, np.memmap) and gf.D.flags.f_contiguous
    seat = SeatState(gf)
    assert np.shares_memory(seat.D, gf.D) and not isinstance(seat.D, np.memmap)
    X, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    free = np.asarray(gf.column_of)[T].min(axis=1) >= 0
    top = np.flatnonzero(free & np.isclose(X[T][:, :, 2], X[:, 2].max()).all(axis=1))
    assert top.size >= 2
    contacts = tuple((7 + k, T[t], np.array([0.2, 0.5, 0.3]), np.array([0.0, 0.0, 1.0])) for k, t in
                     enumerate(top[[0, -1]]))
    lam = np.array([-0.8, -1.3])
    cc = loaded_set(gf, contacts)
    seat.set_forces(cc, lam)
    u = hand_field(gf, contacts, lam)
    assert np.abs(u).max() > 0.0
    np.testing.assert_allclose(seat.u, u, rtol=1e-10, atol=1e-14 * np.abs(u).max())
    np.testing.assert_allclose(seat.u_at(cc.V), u[cc.V], rtol=1e-10, atol=1e-14 * np.abs(u).max())
    np.testing.assert_allclose(seat.peak_field(), _brute_peak(gf, [(contacts, lam, False)], u), rtol=1e-10,
                               atol=1e-14 * np.abs(u).max())
