"""The compiled kernels (numba) against their numpy references."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba")

from hailstorm.runtime import compiled as C  # noqa: E402
from hailstorm.runtime import patches, soft_contacts  # noqa: E402
from hailstorm.runtime.collide import SurfaceIndex  # noqa: E402
from hailstorm.runtime.scene import Scene, SceneError  # noqa: E402
from hailstorm.runtime.storm import Storm, run_storm  # noqa: E402
from test_hail import plate_gf  # noqa: E402


@pytest.fixture(scope="module")
def gf():
    return plate_gf()


def _bumpy(gf):
    """A lifted, bumpy copy of the plate (no two triangles coplanar)."""
    V = gf.vertices.copy()
    V[:, 2] = 0.01 * np.sin(40 * V[:, 0]) * np.cos(30 * V[:, 1])
    return V, np.asarray(gf.triangles)


def test_nearest_sample_is_exact(gf):
    """The grid's nearest-sample search equals the k-d tree's, inside and far outside the grid."""
    V, T = _bumpy(gf)
    idx = SurfaceIndex(V, T)
    g = idx.grid
    rng = np.random.default_rng(1)
    P = rng.uniform(V.min(axis=0) - 0.05, V.max(axis=0) + 0.05, (500, 3))
    ref, _ = idx.tree.query(P, k=1)
    from hailstorm.runtime.compiled.grid import _nearest_sample

    got = np.array([_nearest_sample(p, g.lo, g.h, g.dims, g.start, g.items, g.points) for p in P])
    np.testing.assert_allclose(got, ref, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("deformed", [False, True])
def test_closest_points_match_the_numpy_query(gf, deformed):
    """Same hits, distances and points as SurfaceIndex.query (the triangle may differ only
    where two triangles share the closest point: a tie)."""
    V, T = _bumpy(gf)
    idx = SurfaceIndex(V, T)
    rng = np.random.default_rng(2)
    Q = rng.uniform(V.min(axis=0) - 0.01, V.max(axis=0) + 0.01, (400, 3))
    reach = rng.uniform(0.001, 0.03, 400)
    D = np.asfortranarray(gf.D)
    cols = np.array([3 * 40 + 2, 3 * 41 + 2, 3 * 60 + 0])
    fv = np.array([-20.0, -15.0, 7.0])
    u = (D[:, cols] @ fv).reshape(-1, 3)
    kw, md = {}, 0.0
    if deformed:
        md = 1.5 * float(np.linalg.norm(u, axis=1).max())
        assert md > 1e-3  # the deformation moves the surface by more than the rounding
        kw = dict(D=D, cols=cols, forces=fv, max_displacement=md)
    ref = idx.query(Q, reach, displacement=(lambda v: u[v]) if deformed else None, max_displacement=md)
    tri, bary, point, dist = C.closest_points(idx.grid, idx.sample_radius, idx.vertices, idx.triangles, Q, reach,
                                              **kw)
    hit = ref.triangle >= 0
    assert 50 < hit.sum() < 350  # hits and misses
    np.testing.assert_array_equal(tri >= 0, hit)
    np.testing.assert_allclose(dist[hit], ref.distance[hit], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(point[hit], ref.point[hit], atol=1e-12)
    assert np.all(np.isinf(dist[~hit])) and np.all(np.isnan(point[~hit]))
    assert np.mean(tri[hit] == ref.triangle[hit]) > 0.95
    np.testing.assert_allclose(bary[hit].sum(axis=1), 1.0, rtol=1e-14)
    # the barycentric coordinates reproduce the point on the (deformed) triangle they name
    X = V + ((D[:, cols] @ fv).reshape(-1, 3) if deformed else 0.0)
    np.testing.assert_allclose(np.einsum("kj,kjd->kd", bary[hit], X[T[tri[hit]]]), point[hit], atol=1e-12)


def test_near_set_matches_numpy(gf):
    """The compiled broad phase decides near/far and updates the budgets as the numpy one."""
    sc = Scene(duration=0.1, stones=0, r_min=0.003, r_max=0.008, backend="numpy")
    st = Storm(gf, sc, spawn=False)
    rng = np.random.default_rng(3)
    lo, hi = st.lo, st.hi
    n = 300
    pos = rng.uniform(lo - 0.03, hi + np.array([0.03, 0.03, 0.08]), (n, 3))
    vel = rng.normal(0.0, 5.0, (n, 3))
    st.add_stones(pos, vel, rng.uniform(0.003, 0.008, n))
    st.ctri[rng.random(n) < 0.05] = 0  # a few stones in contact
    st.budget[:] = rng.uniform(-0.01, 0.05, n)
    st._bud_u[:] = rng.uniform(0.0, 0.002, n)
    st._umax_step = 0.001
    live = np.flatnonzero(st.alive)
    b0, u0 = st.budget.copy(), st._bud_u.copy()
    for dt in (5e-4, 5e-3):
        st.budget[:], st._bud_u[:] = b0, u0
        st._compiled = False
        near_ref = st._near_set(live, dt)
        far_ref, b_ref, u_ref = st._far.copy(), st.budget.copy(), st._bud_u.copy()
        st.budget[:], st._bud_u[:] = b0, u0
        st._compiled = True
        near = st._near_set(live, dt)
        np.testing.assert_array_equal(near, near_ref)
        np.testing.assert_array_equal(st._far, far_ref)
        np.testing.assert_allclose(st.budget, b_ref, rtol=1e-13, atol=1e-15)
        np.testing.assert_array_equal(st._bud_u, u_ref)
        assert 0 < near.size < n


def test_patch_weights_match_the_reference(seat_bundle):
    """The compiled patch weights on the curved seat equal the numpy statement of the
    algorithm (tests/reference/patch_weights_ref.py, its own k-d tree search), small to
    large discs; radius 0 gives the barycentric weights bit for bit."""
    from hailstorm.runtime.bundle import load
    from hailstorm.runtime.contact.weights import patch_weights
    from reference.patch_weights_ref import patch_weights_ref

    gf = load(seat_bundle)
    usable = np.flatnonzero((gf.contactable | gf.fixed)[gf.triangles].all(axis=1))
    rng = np.random.default_rng(4)
    k = 60
    t = rng.choice(usable, k)
    b = rng.dirichlet([1.0, 1.0, 1.0], k)
    a = rng.uniform(0.0, 0.03, k)
    a[:5] = 0.0  # point contacts: the barycentric weights
    v1, w1 = patch_weights(gf, t, b, a)
    ref = patch_weights_ref(gf, t, b, a)
    n = gf.vertices.shape[0]
    for i in range(k):
        d0, d1 = np.zeros(n), np.zeros(n)
        np.add.at(d0, ref[i][0], ref[i][1])
        np.add.at(d1, v1[i], w1[i])
        np.testing.assert_allclose(d1, d0, atol=1e-13)
    np.testing.assert_array_equal(w1[:5, :3], b[:5])
    assert (w1 > 0).sum(axis=1).max() > 10  # some patches span many vertices


@pytest.mark.parametrize("integrator, mode, patch, dt, rel", [
    ("exact", "frictionless", "hertz", 5e-4, 1e-6),
    ("exact", "sticky", "none", 5e-4, 1e-6),
    ("implicit", "frictionless", "hertz", 2e-4, 0.05),
    ("symplectic", "sticky", "hertz", 2e-5, 0.05),
])
def test_storm_backends_agree(gf, integrator, mode, patch, dt, rel):
    """The same storm on the flat plate (no ties that change a normal) on both backends.

    ``exact`` takes one sub-step per step on both: the same impacts, sub-steps and
    forces to rounding. The adaptive implicit and symplectic integrators size their
    sub-steps from the gaps, which the compiled path measures where the numpy one
    reuses or bounds them: the same impacts, forces within a few percent."""
    sc = Scene(duration=0.06, stones=15, seed=5, spawn_height=0.02, r_min=0.003, r_max=0.008, dt=dt,
               integrator=integrator, mode=mode, patch=patch)
    res = {b: run_storm(gf, dataclasses.replace(sc, backend=b), progress=False).stats for b in ("numpy", "numba")}
    a, b = res["numpy"], res["numba"]
    assert b["backend"] == "numba" and a["backend"] == "numpy"
    assert a["impacts"] == b["impacts"] >= 5
    assert a["hailstones"] == b["hailstones"] and a["retired"] == b["retired"] and a["stones_hit"] == b["stones_hit"]
    assert b["max_contact_force"] == pytest.approx(a["max_contact_force"], rel=rel)
    assert b["max_indentation_m"] == pytest.approx(a["max_indentation_m"], rel=rel)
    assert b["max_penetration_m"] == pytest.approx(a["max_penetration_m"], rel=10 * rel, abs=1e-7)
    if integrator == "exact":
        assert a["substeps"] == b["substeps"]
        assert a["capacitance_rebuilds"] == b["capacitance_rebuilds"]


def test_patch_radii_match_numpy(gf):
    """The compiled patch sizing gives the numpy radii, resizes and cached weights, for
    new contacts and for known ones (with a previous contact set and its forces)."""
    sc = Scene(duration=0.1, stones=0, r_min=0.003, r_max=0.008, backend="numba")
    st = Storm(gf, sc, spawn=False)
    rng = np.random.default_rng(6)
    tris = rng.choice(np.flatnonzero(st.soft), 6, replace=False)
    bary = rng.dirichlet([2.0, 2.0, 2.0], 6)
    X = np.einsum("kj,kjd->kd", bary, gf.vertices[gf.triangles[tris]])
    r = rng.uniform(0.003, 0.008, 6)
    ids = st.add_stones(X + r[:, None] * st.index.normals[tris], rng.normal(0.0, 2.0, (6, 3)), r)
    st.ctri[ids] = tris
    st.cbary[ids] = bary
    for known in (False, True):
        if known:  # a previous set with the first four stones and some forces
            st.cache = soft_contacts.contact_set(st, ids[:4], tris[:4], bary[:4].copy(), ("prev",), st.crad[ids[:4]])
            st.lam = -rng.uniform(0.1, 20.0, 4)
            st.crad[ids[:2]] *= 0.5  # two known contacts whose radius is out of date
        crad0, stats0 = st.crad.copy(), dict(st.stats)
        out = {}
        for compiled in (False, True):
            st.crad[:] = crad0
            st.stats = dict(stats0)
            st._wcache.clear()
            st._compiled = compiled
            a = patches.radii(st, ids, tris)
            out[compiled] = (a, st.crad.copy(), st.stats["patch_resizes"], dict(st._wcache))
        (a0, c0, r0, w0), (a1, c1, r1, w1) = out[False], out[True]
        np.testing.assert_allclose(a1, a0, rtol=1e-12)
        np.testing.assert_allclose(c1, c0, rtol=1e-12)
        assert r1 == r0
        assert r0 >= (1 if known else 0) and np.all(a0 > 0)
        for j in w1:  # the new contacts' weights at their first radius, as numpy cached them
            assert w1[j][:2] == w0[j][:2]
            assert w1[j][2] == pytest.approx(w0[j][2], rel=1e-14)  # the radius (cbrt rounds differently)
            np.testing.assert_array_equal(w1[j][3], w0[j][3])
            np.testing.assert_allclose(w1[j][4], w0[j][4], atol=1e-14)
        assert len(w1) == (2 if known else 6)


def test_backend_choice(gf, monkeypatch):
    """'auto' takes numba when installed; asking for numba without it is a clear error."""
    assert Storm(gf, Scene(backend="auto"), spawn=False).backend == "numba"
    assert Storm(gf, Scene(backend="numpy"), spawn=False).backend == "numpy"
    with pytest.raises(SceneError, match="backend"):
        Scene(backend="fortran")
    monkeypatch.setattr(C, "HAVE_NUMBA", False)
    assert Storm(gf, Scene(backend="auto"), spawn=False).backend == "numpy"
    with pytest.raises(SceneError, match=r"pip install"):
        Storm(gf, Scene(backend="numba"), spawn=False)


def _random_contact_set(rng):
    """A random coupled contact set in constrained coordinates: frictionless (one
    component per contact) or sticky (three, with the contact normals as weights)."""
    from hailstorm.runtime.hail import _inv_spd

    s = int(rng.integers(1, 5))
    sticky = bool(rng.random() < 0.3)
    n = 3 * s if sticky else s
    A = rng.normal(size=(n, n))
    W = (A @ A.T + n * np.eye(n)) * 1e-4
    nk = rng.normal(size=(s, 3))
    nk /= np.linalg.norm(nk, axis=1, keepdims=True)
    a = rng.normal(size=n) * 1e-3
    return dict(
        sticky=sticky, W=W, K=_inv_spd(W), a=a, q=a + rng.normal(size=n) * 1e-3, v=rng.normal(size=n) * 2.0,
        g=rng.normal(size=n) * 5.0,
        m=np.repeat(rng.uniform(5e-4, 2e-3, s), 3) if sticky else rng.uniform(5e-4, 2e-3, n),
        group=np.repeat(np.arange(s), 3) if sticky else np.arange(n),
        wts=nk.ravel() if sticky else np.ones(n),
        always=np.repeat(rng.random(s) < 0.2, 3) if sticky else rng.random(n) < 0.2,
    )


def _assert_same_step(got, ref):
    qn, vn, act, force, seat, *peaks = got
    np.testing.assert_array_equal(act, ref.active)
    np.testing.assert_allclose(qn, ref.q, rtol=0, atol=1e-14)
    np.testing.assert_allclose(vn, ref.v, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(seat, ref.seat_force, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(force, ref.force, rtol=1e-9, atol=1e-9)
    if peaks:  # the exact step's peaks inside the step
        np.testing.assert_allclose(peaks[0], ref.peak_seat_force, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(peaks[1], ref.peak_ubar, rtol=0, atol=1e-14)
    return int((~act).any())


def test_exact_step_matches_numpy():
    """The compiled exact integrator reproduces hailstorm.runtime.hail's on random coupled contact
    sets: frictionless and sticky, s = 1..4, unilateral releases, resting (always damped)
    components, the same active sets and the same peaks inside the step."""
    from hailstorm.runtime.hail import contact_step, damping_coefficients

    rng = np.random.default_rng(7)
    released = 0
    for _ in range(300):
        c = _random_contact_set(rng)
        damping = damping_coefficients(c["K"], c["m"], 0.5, integrator="exact")
        ref = contact_step(c["q"], c["v"], c["a"], c["m"], c["g"], 5e-4, K=c["K"], W=c["W"], damping=damping,
                           integrator="exact", unilateral=True, group=c["group"] if c["sticky"] else None,
                           normal_of=c["wts"] if c["sticky"] else None, always_damped=c["always"])
        *got, ok = C.exact_step(c["q"], c["v"], c["a"], c["m"], c["g"], 5e-4, c["K"], c["W"], np.diag(damping), True,
                                c["group"], c["wts"], c["always"], 1e10, 1e-10)
        assert ok
        released += _assert_same_step(got, ref)
    assert released > 20  # the active-set (release) path is exercised


@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_substep_contacts_and_damping_match_numpy(integrator):
    """The compiled backward-Euler / symplectic contact step and its dashpot reproduce
    hailstorm.runtime.hail's on random coupled sets (frictionless and sticky, releases)."""
    from hailstorm.runtime.hail import _X_GRID, _Z_GRID, contact_modes, contact_step, modal_damping

    rng = np.random.default_rng(8)
    released = 0
    for _ in range(200):
        c = _random_contact_set(rng)
        dt = float(rng.choice([2e-5, 2e-4]))
        e = float(rng.uniform(0.2, 0.9))
        damping = modal_damping(c["K"], c["m"], e, dt=dt, integrator="implicit" if integrator == "implicit" else "exact")
        got = C.substep_damping(*contact_modes(c["K"], c["m"]), e, dt, integrator == "implicit", _X_GRID, _Z_GRID)
        np.testing.assert_allclose(got, damping, rtol=1e-12, atol=1e-12 * np.abs(damping).max())
        ref = contact_step(c["q"], c["v"], c["a"], c["m"], c["g"], dt, K=c["K"], W=c["W"], damping=damping,
                           integrator=integrator, unilateral=True, group=c["group"] if c["sticky"] else None,
                           normal_of=c["wts"] if c["sticky"] else None)
        released += _assert_same_step(
            C.substep_contacts(c["q"], c["v"], c["a"], c["m"], c["g"], dt, c["K"], c["W"], damping,
                               integrator == "implicit", True, c["group"], c["wts"], 1e10, 1e-10), ref)
    assert released > 20


# ---------------------------------------------------------------------------
# the contact core's block kernels (hailstorm.runtime.compiled.blocks), against dense algebra on D
# ---------------------------------------------------------------------------
def _contact_lists(gf, rng, s, patch):
    """s random contacts on the plate (some on the clamp): vertex lists, weights, normals."""
    from hailstorm.runtime.contact.weights import locate, patch_weights, triangle_normals

    usable = np.flatnonzero((gf.contactable | gf.fixed)[gf.triangles].all(axis=1))
    t = rng.choice(usable, s)
    b = rng.dirichlet([1.0, 1.0, 1.0], s)
    n = triangle_normals(gf.vertices, gf.triangles[t])
    a = rng.uniform(0.0, 0.03, s) if patch else None
    pv, w = (gf.triangles[t], b) if a is None else patch_weights(gf, t, b, a, n)
    V, loc = locate(pv)
    return t, b, n, a, V, loc, w


def _dense_block(gf, rows, cols):
    """D[rows, cols] by plain fancy indexing of the dense D, zero columns where cols < 0."""
    D = np.asarray(gf.D)
    return np.where(cols[None, :] >= 0, D[np.ix_(rows, np.maximum(cols, 0))], 0.0)


@pytest.mark.parametrize("patch", [False, True])
@pytest.mark.parametrize("s", [1, 12, 40])
def test_contact_blocks_match_dense_algebra(gf, s, patch):
    """vertex_block is D_VV exactly (zero columns at clamped vertices); W = G^T D_VV G and
    D_VV G from weighted_rows / contact_compliance equal the dense products with G (B, or
    B N) to rounding, both modes; constraint_rows is weighted_rows of vertex_block exactly; weighted_rows over D.T is the full-surface response
    D[:, V] B; columns_times is D[:, cols] g."""
    from hailstorm.runtime.contact.compliance import column_dofs, dof3, vertex_block
    from hailstorm.runtime.contact.contact_set import _response_columns, contact_compliance
    from hailstorm.runtime.contact.weights import dense_B

    gf = dataclasses.replace(gf, D=np.asfortranarray(gf.D))
    rng = np.random.default_rng(s + 100 * patch)
    t, b, n, a, V, loc, w = _contact_lists(gf, rng, s, patch)
    cols = column_dofs(gf, V)
    assert (cols < 0).any() or s < 40  # the larger sets reach the clamp
    D_VV = _dense_block(gf, dof3(V), cols)
    M = C.vertex_block(V, gf.D.T, gf.column_of)
    np.testing.assert_array_equal(M.T, D_VV)
    np.testing.assert_array_equal(vertex_block(gf, V), D_VV)
    B = dense_B(V.size, loc, w)
    for sticky in (True, False):
        mode = "sticky" if sticky else "frictionless"
        G = B if sticky else np.einsum("rkj,kj->rk", B.reshape(B.shape[0], s, 3), n)
        Y = C.weighted_rows(M, np.arange(V.size), loc, w, n, sticky)
        np.testing.assert_array_equal(C.blocks.constraint_rows(gf.D.T, gf.column_of, V, loc, w, n, sticky), Y)
        W = C.contact_compliance(Y, loc, w, n, sticky)
        W_ref = G.T @ D_VV @ G
        W_ref = 0.5 * (W_ref + W_ref.T)
        np.testing.assert_allclose(W, W_ref, rtol=0, atol=1e-13 * np.abs(W_ref).max())
        np.testing.assert_array_equal(W, W.T)
        np.testing.assert_array_equal(contact_compliance(D_VV, loc, w, n, mode), W)
        np.testing.assert_allclose(Y.T, D_VV @ G, rtol=0, atol=1e-13 * np.abs(D_VV).max())
    R = _response_columns(gf, cols, loc, w)
    R_ref = _dense_block(gf, np.arange(gf.D.shape[0]), cols) @ B
    np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-13 * np.abs(R_ref).max())
    g = rng.normal(size=cols.size)
    u_ref = _dense_block(gf, np.arange(gf.D.shape[0]), cols) @ g
    np.testing.assert_allclose(C.columns_times(gf.D.T, cols, g), u_ref, rtol=0, atol=1e-13 * np.abs(u_ref).max())


def test_contact_api_calls_the_kernels(gf, monkeypatch):
    """Bilateral point contacts take the one-call point_contacts, everything else the block
    kernels (also for a row-major D, read through a column-major copy); the two paths agree
    to rounding with each other and with a dense solve of W."""
    import hailstorm.runtime.contact.compliance
    import hailstorm.runtime.contact.contact_set
    import hailstorm.runtime.contact.solve
    from hailstorm.runtime.contact import capacitance, policy, solve_contacts
    from hailstorm.runtime.contact.compliance import column_dofs, dof3
    from hailstorm.runtime.contact.weights import dense_B

    calls = []

    class Spy:  # the modules' handle on the kernels, recording which are fetched
        def __getattr__(self, name):
            calls.append(name)
            return getattr(C.blocks, name)

    for mod in (hailstorm.runtime.contact.solve, hailstorm.runtime.contact.contact_set,
                hailstorm.runtime.contact.compliance):
        monkeypatch.setattr(mod, "kernels", Spy())
    rng = np.random.default_rng(5)
    t, b, n, a, V, loc, w = _contact_lists(gf, rng, 6, False)
    t = np.where(gf.fixed[gf.triangles[t]].all(axis=1), t[0], t)  # no rigid contact: the fast path takes all
    ubar = -1e-4 * n
    F = dataclasses.replace(gf, D=np.asfortranarray(gf.D))
    # dense reference: f = (B^T D_VV B)^-1 ubar, u = D[:, V] B f
    V, loc = np.unique(F.triangles[t], return_inverse=True)
    cols = column_dofs(F, V)
    B = dense_B(V.size, loc.reshape(-1, 3), b)
    f_ref = np.linalg.solve(B.T @ _dense_block(F, dof3(V), cols) @ B, ubar.ravel())
    u_ref = (_dense_block(F, np.arange(F.D.shape[0]), cols) @ B @ f_ref).reshape(-1, 3)

    def same(x, y):
        for p, q in ((x.forces, y.forces), (x.surface_displacement, y.surface_displacement),
                     (x.contact_displacement, y.contact_displacement), (x.vertex_forces, y.vertex_forces)):
            if q is None:
                assert p is None
                continue
            np.testing.assert_allclose(p, q, rtol=0, atol=1e-12 * np.abs(q).max())
        np.testing.assert_array_equal(x.vertices, y.vertices)
        np.testing.assert_array_equal(x.active, y.active)

    fast = solve_contacts(F, t, b, ubar)
    assert calls == ["point_contacts"]
    np.testing.assert_allclose(fast.forces.ravel(), f_ref, rtol=0, atol=1e-10 * np.abs(f_ref).max())
    np.testing.assert_allclose(fast.surface_displacement, u_ref, rtol=0, atol=1e-10 * np.abs(u_ref).max())
    calls.clear()
    uni = solve_contacts(F, t, b, ubar, unilateral=True)
    assert calls == ["constraint_rows", "contact_compliance", "columns_times"]
    same(uni, fast)  # pressing contacts: none is released
    calls.clear()
    cap = capacitance(F, t, b)
    cap.keep_response()
    assert calls == ["constraint_rows", "contact_compliance", "weighted_rows"]
    calls.clear()
    np.testing.assert_array_equal(cap.D_VV, _dense_block(F, dof3(V), cols))  # gathered on first use
    assert calls == ["vertex_block"]
    calls.clear()
    monkeypatch.setattr(policy, "POINT_FAST_MAX", t.size - 1)  # too many for the fast path
    same(solve_contacts(F, t, b, ubar), fast)
    assert calls == ["constraint_rows", "contact_compliance", "columns_times"]
    calls.clear()
    same(solve_contacts(F, t, b, ubar, rows=None), dataclasses.replace(fast, surface_displacement=None))
    assert calls == ["constraint_rows", "contact_compliance"]  # the contact displacement from (D_VV G)^T
    calls.clear()
    Crow = dataclasses.replace(gf, D=np.ascontiguousarray(gf.D))
    same(solve_contacts(Crow, t, b, ubar), fast)
    assert calls == ["constraint_rows", "contact_compliance", "columns_times"]


def test_point_contacts_fast_path(gf):
    """The one-call solve of bilateral point contacts equals the general path (random sets,
    both modes, with and without the surface), and hands every special case back to it
    with its code: invalid input 1, a vertex without a column of D 2, a rigid contact 3,
    coincident contacts (pseudo-inverse) 4."""
    from hailstorm.runtime.contact import policy, solve_contacts, triangle_normals

    F = dataclasses.replace(gf, D=np.asfortranarray(gf.D))
    T = np.asarray(F.triangles)
    soft = np.flatnonzero(F.contactable[T].all(axis=1))
    rng = np.random.default_rng(8)
    for trial in range(40):
        s = int(rng.integers(1, 25))
        t = rng.choice(soft, s)
        b = rng.dirichlet([1.0, 1.0, 1.0], s)
        nrm = triangle_normals(F.vertices, T[t])
        ubar = -1e-4 * nrm + rng.normal(scale=3e-5, size=(s, 3))
        mode = ("sticky", "frictionless")[trial % 2]
        rows = ("all", None)[(trial // 2) % 2]
        got = solve_contacts(F, t, b, ubar, mode=mode, rows=rows)
        ref = solve_contacts(F, t, b, ubar, mode=mode, rows=rows, normals=nrm)  # explicit normals: the general path
        for p, q in ((got.forces, ref.forces), (got.contact_displacement, ref.contact_displacement),
                     (got.vertex_forces, ref.vertex_forces), (got.surface_displacement, ref.surface_displacement)):
            if q is None:
                assert p is None
                continue
            np.testing.assert_allclose(p, q, rtol=0, atol=1e-10 * np.abs(q).max())
        np.testing.assert_array_equal(got.vertices, ref.vertices)
        assert got.active.all() and not got.rigid.any() and got.iterations == 1

    def code(t, b, contactable=None, sticky=True):
        t = np.asarray(t, dtype=np.int64)
        return C.point_contacts(F.D.T, F.column_of, F.contactable if contactable is None else contactable, F.fixed,
                                T, F.vertices, t, np.asarray(b, float), np.full((t.size, 3), -1e-4), sticky, True,
                                policy.BARY_SUM_TOL, policy.BARY_NEG_TOL, policy.COND_LIMIT, policy.RIGID_WEIGHT)[0]

    third = [1 / 3, 1 / 3, 1 / 3]
    assert code([soft[0]], [third]) == 0
    assert code([soft[0]], [[0.2, 0.3, 0.6]]) == 1  # does not sum to 1
    assert code([T.shape[0]], [third]) == 1  # out of range
    crippled = F.contactable.copy()
    crippled[T[soft[0], 0]] = False
    assert code([soft[0]], [third], contactable=crippled) == 2
    rigid = np.flatnonzero(F.fixed[T].all(axis=1))[0]
    assert code([soft[0], rigid], [third, third]) == 3
    assert code([soft[0], soft[0]], [third, third]) == 4
    assert code([soft[0], soft[0]], [third, third], sticky=False) == 4
