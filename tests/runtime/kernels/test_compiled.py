"""The compiled kernels (numba) against their numpy references: the contact steps (the
storm's geometry kernels are in test_storm_kernels) and the contact API's blocks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba")

from hailstorm.runtime import compiled as C  # noqa: E402


def test_patch_weights_match_the_reference(seat_bundle):
    """The compiled patch weights on the curved seat equal the numpy statement of the
    algorithm (tests/reference/patch_weights_ref.py, its own k-d tree search), small to
    large discs; radius 0 gives the barycentric weights exactly (one code path)."""
    from hailstorm.runtime.bundle.read import load
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


def _random_contact_set(rng):
    """A random coupled contact set in constrained coordinates: frictionless (one
    component per contact) or sticky (three, with the contact normals as weights)."""
    from hailstorm.runtime.contact.policy import spd_inverse

    s = int(rng.integers(1, 5))
    sticky = bool(rng.random() < 0.3)
    n = 3 * s if sticky else s
    A = rng.normal(size=(n, n))
    W = (A @ A.T + n * np.eye(n)) * 1e-4
    nk = rng.normal(size=(s, 3))
    nk /= np.linalg.norm(nk, axis=1, keepdims=True)
    a = rng.normal(size=n) * 1e-3
    return dict(
        sticky=sticky, W=W, K=spd_inverse(W), a=a, q=a + rng.normal(size=n) * 1e-3, v=rng.normal(size=n) * 2.0,
        g=rng.normal(size=n) * 5.0,
        m=np.repeat(rng.uniform(5e-4, 2e-3, s), 3) if sticky else rng.uniform(5e-4, 2e-3, n),
        group=np.repeat(np.arange(s), 3) if sticky else np.arange(n),
        wts=nk.ravel() if sticky else np.ones(n),
        always=np.repeat(rng.random(s) < 0.2, 3) if sticky else rng.random(n) < 0.2,
    )


def _critical_damping(K, m):
    """The dashpot that damps every normal mode of ``M^-1/2 K M^-1/2`` critically
    (zeta = 1): the state matrix is defective (the exact step's matrix exponential)."""
    from hailstorm.runtime.storm.hail import contact_modes

    om2, Phi, sqm = contact_modes(K, m)
    P = Phi * sqm[:, None]
    C = (P * (2.0 * np.sqrt(om2))) @ P.T
    return 0.5 * (C + C.T)


def _assert_same_step(got, ref, rel=None):
    """The kernel's step ``got`` is the reference's: to rounding (``rel`` None), or to ``rel``
    of each array's largest entry (another evaluation of the same trajectory)."""
    qn, vn, act, force, seat, *peaks = got
    np.testing.assert_array_equal(act, ref.active)
    if rel is not None:
        pairs = [(qn, ref.q), (vn, ref.v), (seat, ref.seat_force), (force, ref.force)]
        if peaks:
            pairs += [(peaks[0], ref.peak_seat_force), (peaks[1], ref.peak_ubar)]
        for x, y in pairs:
            np.testing.assert_allclose(x, y, rtol=0, atol=rel * np.abs(y).max())
        return int((~act).any())
    np.testing.assert_allclose(qn, ref.q, rtol=0, atol=1e-14)
    np.testing.assert_allclose(vn, ref.v, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(seat, ref.seat_force, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(force, ref.force, rtol=1e-9, atol=1e-9)
    if peaks:  # the exact step's peaks inside the step
        np.testing.assert_allclose(peaks[0], ref.peak_seat_force, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(peaks[1], ref.peak_ubar, rtol=0, atol=1e-14)
    return int((~act).any())


def _assert_same_solution(x, y, rel):
    """Two contact solutions agree: forces and displacements to ``rel`` of the largest entry of
    ``y``'s (absent in both, or in neither), the same loaded vertices."""
    for name in ("forces", "surface_displacement", "contact_displacement", "vertex_forces"):
        p, q = getattr(x, name), getattr(y, name)
        if q is None:
            assert p is None
            continue
        np.testing.assert_allclose(p, q, rtol=0, atol=rel * np.abs(q).max())
    np.testing.assert_array_equal(x.vertices, y.vertices)


def _as_tuple(res):
    return (res.q, res.v, res.active, res.force, res.seat_force, res.peak_seat_force, res.peak_ubar)


def test_exact_step_matches_the_reference():
    """The compiled exact integrator (and hail.contact_step, its wrapper) reproduces the numpy
    statement of the algorithm (tests/reference/contact_step_ref.py) on random coupled contact
    sets: frictionless and sticky, s = 1..4, unilateral on and off, dashpot on and off, resting
    (always damped) components, critically damped sets (a defective modal basis: the kernel's
    matrix exponential, the reference's scipy.linalg.expm); the same active sets and the same
    peaks inside the step."""
    from hailstorm.runtime.storm.hail import contact_step, damping_coefficients
    from reference.contact_step_ref import contact_step_ref

    rng = np.random.default_rng(7)
    released = critical = 0
    for it in range(400):
        c = _random_contact_set(rng)
        unilateral = bool(it % 4)
        kind = rng.choice(["restitution", "none", "critical"], p=[0.6, 0.15, 0.25])
        if kind == "restitution":
            damping = np.diag(damping_coefficients(c["K"], c["m"], 0.5, integrator="exact"))
        elif kind == "none":
            damping = np.zeros((c["m"].size,) * 2)
        else:
            damping = _critical_damping(c["K"], c["m"])
            critical += 1
        kw = dict(K=c["K"], W=c["W"], damping=damping, integrator="exact", unilateral=unilateral,
                  group=c["group"], normal_of=c["wts"], always_damped=c["always"])
        ref = contact_step_ref(c["q"], c["v"], c["a"], c["m"], c["g"], 5e-4, **kw)
        got = C.exact_step(c["q"], c["v"], c["a"], c["m"], c["g"], 5e-4, c["K"], c["W"], damping, unilateral,
                           c["group"], c["wts"], c["always"], 1e10, 1e-10)
        assert len(got) == 7  # every case covered: no "not covered" flag
        # (repeated products of one expm against scipy's expm at each sample time: rounding apart)
        released += _assert_same_step(got, ref, rel=1e-8 if kind == "critical" else None)
        wrapped = contact_step(c["q"], c["v"], c["a"], c["m"], c["g"], 5e-4, **kw)
        for x, y in zip(_as_tuple(wrapped), got):
            np.testing.assert_array_equal(x, y)
    assert released > 20 and critical > 50  # the active-set (release) path and the expm path are exercised


@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_substep_contacts_and_damping_match_the_reference(integrator):
    """The compiled backward-Euler / symplectic contact step (and hail.contact_step, its wrapper)
    reproduces the numpy statement (tests/reference/contact_step_ref.py) on random coupled sets
    (frictionless and sticky, unilateral on and off, dashpot on and off, releases); the compiled
    dashpot is hail.modal_damping."""
    from hailstorm.runtime.storm.hail import _X_GRID, _Z_GRID, contact_modes, contact_step, modal_damping
    from reference.contact_step_ref import contact_step_ref

    rng = np.random.default_rng(8)
    released = 0
    for it in range(200):
        c = _random_contact_set(rng)
        unilateral = bool(it % 4)
        dt = float(rng.choice([2e-5, 2e-4]))
        e = float(rng.uniform(0.2, 0.9))
        damping = modal_damping(c["K"], c["m"], e, dt=dt, integrator="implicit" if integrator == "implicit" else "exact")
        got = C.substep_damping(*contact_modes(c["K"], c["m"]), e, dt, integrator == "implicit", _X_GRID, _Z_GRID)
        np.testing.assert_allclose(got, damping, rtol=1e-12, atol=1e-12 * np.abs(damping).max())
        if it % 5 == 0:
            damping = np.zeros_like(damping)
        kw = dict(K=c["K"], W=c["W"], damping=damping, integrator=integrator, unilateral=unilateral,
                  group=c["group"], normal_of=c["wts"])
        ref = contact_step_ref(c["q"], c["v"], c["a"], c["m"], c["g"], dt, **kw)
        got = C.substep_contacts(c["q"], c["v"], c["a"], c["m"], c["g"], dt, c["K"], c["W"], damping,
                                 integrator == "implicit", unilateral, c["group"], c["wts"], 1e10, 1e-10)
        released += _assert_same_step(got, ref)
        wrapped = contact_step(c["q"], c["v"], c["a"], c["m"], c["g"], dt, **kw)
        for x, y in zip(_as_tuple(wrapped)[:5], got):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(wrapped.peak_seat_force, got[4])
    assert released > 20


# ---------------------------------------------------------------------------
# the contact core's block kernels (hailstorm.runtime.compiled.blocks, .wmatrix, .point_solve), against dense
# algebra on D
# ---------------------------------------------------------------------------
def _contact_lists(gf, rng, s, patch):
    """s random contacts on the plate (some on the clamp): vertex lists, weights, normals."""
    from hailstorm.runtime.contact.normals import triangle_normals
    from hailstorm.runtime.contact.weights import locate, patch_weights

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
    from hailstorm.runtime.bundle.compliance import column_dofs, dof3, response_columns, vertex_block
    from hailstorm.runtime.contact.capacitance_blocks import contact_compliance
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
    R = response_columns(gf, cols, loc, w)
    R_ref = _dense_block(gf, np.arange(gf.D.shape[0]), cols) @ B
    np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-13 * np.abs(R_ref).max())
    g = rng.normal(size=cols.size)
    u_ref = _dense_block(gf, np.arange(gf.D.shape[0]), cols) @ g
    np.testing.assert_allclose(C.columns_times(gf.D.T, cols, g), u_ref, rtol=0, atol=1e-13 * np.abs(u_ref).max())


def test_contact_kernels_grouping_edges(gf):
    """The kernels' passes (constraint_rows: one vertex per pass, prefetching ahead;
    columns_times: eight columns, then four, then one) on
    contacts with 1 to 8 live vertices, zero weights and clamped vertices among them, and
    sets of 0 to 17 columns with clamped (-1) entries: W and (D_VV G)^T equal the dense
    products with G to rounding, constraint_rows is weighted_rows of vertex_block exactly
    (the same sums in the same order), columns_times is D[:, cols] g."""
    from hailstorm.runtime.bundle.compliance import column_dofs, dof3
    from hailstorm.runtime.contact.weights import dense_B, locate

    gf = dataclasses.replace(gf, D=np.asfortranarray(gf.D))
    rng = np.random.default_rng(11)
    free = np.flatnonzero(gf.contactable)
    clamped = np.flatnonzero(gf.fixed & ~gf.contactable)
    assert clamped.size and free.size > 40
    s, P = 8, 8
    verts = np.empty((s, P), dtype=np.intp)
    w = np.zeros((s, P))
    for k in range(s):  # contact k: k + 1 weighted vertices (some clamped, one zero weight)
        vk = rng.choice(free, P, replace=False)
        if k % 3 == 1:
            vk[k // 2] = rng.choice(clamped)
        verts[k] = vk
        w[k, :k + 1] = rng.dirichlet(np.ones(k + 1))
        if k >= 4:
            w[k, 1] = 0.0  # a zero weight inside the list
    V, loc = locate(verts)
    cols = column_dofs(gf, V)
    assert (cols < 0).any()
    n = rng.normal(size=(s, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    D_VV = _dense_block(gf, dof3(V), cols)
    M = C.vertex_block(V, gf.D.T, gf.column_of)
    B = dense_B(V.size, loc, w)
    for sticky in (True, False):
        G = B if sticky else np.einsum("rkj,kj->rk", B.reshape(B.shape[0], s, 3), n)
        Y = C.blocks.constraint_rows(gf.D.T, gf.column_of, V, loc, w, n, sticky)
        np.testing.assert_array_equal(Y, C.weighted_rows(M, np.arange(V.size), loc, w, n, sticky))
        np.testing.assert_allclose(Y.T, D_VV @ G, rtol=0, atol=1e-13 * np.abs(D_VV).max())
        W = C.contact_compliance(Y, loc, w, n, sticky)
        W_ref = G.T @ D_VV @ G
        np.testing.assert_allclose(W, 0.5 * (W_ref + W_ref.T), rtol=0, atol=1e-13 * np.abs(W_ref).max())
    all_cols = column_dofs(gf, np.concatenate([free[:5], clamped[:1]]))
    for k in range(18):
        c = all_cols[:k]
        g = rng.normal(size=k)
        u_ref = _dense_block(gf, np.arange(gf.D.shape[0]), c) @ g
        np.testing.assert_allclose(C.columns_times(gf.D.T, c, g), u_ref, rtol=0,
                                   atol=1e-13 * max(np.abs(u_ref).max(initial=0.0), 1e-300))


def test_contact_api_calls_the_kernels(gf, monkeypatch):
    """Bilateral point contacts take the one-call point_contacts, everything else the block
    kernels (also for a row-major D, read through a column-major copy); the two paths agree
    to rounding with each other and with a dense solve of W."""
    import hailstorm.runtime.bundle.compliance
    import hailstorm.runtime.contact.capacitance_blocks
    import hailstorm.runtime.contact.capacitance_build
    import hailstorm.runtime.contact.solve
    from hailstorm.runtime.contact import capacitance, policy, solve_contacts
    from hailstorm.runtime.bundle.compliance import column_dofs, dof3
    from hailstorm.runtime.contact.weights import dense_B

    calls = []

    class Spy:  # a module's handle on a kernel module, recording which kernels are fetched
        def __init__(self, kernels):
            self.kernels = kernels

        def __getattr__(self, name):
            calls.append(name)
            return getattr(self.kernels, name)

    for mod, handle, kernels in ((hailstorm.runtime.contact.solve, "kernels", C.point_solve),
                                 (hailstorm.runtime.contact.capacitance_build, "w_kernels", C.wmatrix),
                                 (hailstorm.runtime.contact.capacitance_blocks, "kernels", C.blocks),
                                 (hailstorm.runtime.contact.capacitance_blocks, "w_kernels", C.wmatrix),
                                 (hailstorm.runtime.bundle.compliance, "kernels", C.blocks)):
        assert getattr(mod, handle) is kernels
        monkeypatch.setattr(mod, handle, Spy(kernels))
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
        _assert_same_solution(x, y, 1e-12)
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
        _assert_same_solution(got, ref, 1e-10)
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


EPS = np.finfo(float).eps


def _close_to_rounding(x, ref, cond, n, what=""):
    """``x`` equals ``ref`` to what LAPACK's backward-stable algorithms guarantee: a relative error of
    ``c n eps cond`` (c = 10, a generous constant for the growth factor). Two LAPACK builds (numpy's and
    scipy's OpenBLAS, or one build on two CPUs) differ by a few ulps times the conditioning, so the
    comparison is never exact."""
    scale = max(np.abs(ref).max(), np.finfo(float).tiny)
    assert np.abs(x - ref).max() <= 10 * max(n, 1) * EPS * max(cond, 1.0) * scale, what


def test_lapack_solve_is_numpys_to_rounding():
    """The compiled dense solve (LAPACK dgesv called directly, without numba's copy-in) solves
    well and badly conditioned systems to LAPACK's backward-error bound and agrees with
    np.linalg.solve to cond(A) times the rounding, for strided inputs too; it raises LinAlgError
    as np.linalg.solve does (singular matrix, inf or NaN)."""
    from hailstorm.runtime.compiled.lapack import solve

    rng = np.random.default_rng(12)
    for n in (1, 2, 3, 5, 12, 40):
        for _ in range(20):
            A = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-8, 8)
            if rng.random() < 0.3:
                A = A @ A.T + 1e-9 * np.eye(n)  # symmetric, ill-conditioned
            b = rng.normal(size=n)
            x = solve(A, b)
            # backward error of LU with partial pivoting: |A x - b| <= c n eps (|A| |x| + |b|)
            resid = np.abs(A @ x - b).max()
            assert resid <= 10 * n * EPS * (np.abs(A).sum(axis=1).max() * np.abs(x).max() + np.abs(b).max())
            _close_to_rounding(x, np.linalg.solve(A, b), np.linalg.cond(A), n)
    M = rng.normal(size=(8, 8))
    A, b = M[::2, ::2], M[1::2, 1]  # strided views: the values count, not the layout
    _close_to_rounding(solve(np.ascontiguousarray(A), np.ascontiguousarray(b)), np.linalg.solve(A, b),
                       np.linalg.cond(A), 4)
    assert solve(np.zeros((0, 0)), np.zeros(0)).shape == (0,)
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        solve(np.array([[1.0, 2.0], [2.0, 4.0]]), np.ones(2))
    for bad in (np.inf, np.nan):
        with pytest.raises(np.linalg.LinAlgError, match="infs or NaNs"):
            solve(np.array([[1.0, 0.0], [0.0, bad]]), np.ones(2))
        with pytest.raises(np.linalg.LinAlgError, match="infs or NaNs"):
            solve(np.eye(2), np.array([1.0, bad]))


def test_lapack_cholesky_inverse_eigh_to_rounding():
    """The compiled Cholesky, inverse, Gram product and symmetric eigendecomposition (LAPACK called
    directly, for the storm's SPD inverse) factor, invert and diagonalise to rounding (checked by
    their defining identities, independent of any other LAPACK build) and agree with numpy's to the
    conditioning times the rounding; a matrix that is not positive definite is reported, not
    raised; a singular one raises as np.linalg.inv."""
    from hailstorm.runtime.compiled.lapack import cholesky, eigh, gram, inverse

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 6, 13, 40):
        for _ in range(10):
            M = rng.normal(size=(n, n))
            S = M @ M.T + 10.0 ** rng.uniform(-9, 1) * np.eye(n)
            cS = np.linalg.cond(S)
            L, ok = cholesky(S)
            assert ok
            assert np.array_equal(L, np.tril(L))
            np.testing.assert_allclose(L @ L.T, S, rtol=0, atol=10 * n * EPS * np.abs(S).max())
            _close_to_rounding(L, np.linalg.cholesky(S), cS, n, "cholesky")
            Li = inverse(L)
            np.testing.assert_allclose(Li @ L, np.eye(n), rtol=0, atol=10 * n * EPS * np.sqrt(cS))
            _close_to_rounding(inverse(M), np.linalg.inv(M), np.linalg.cond(M), n, "inverse")
            G = gram(Li)
            np.testing.assert_allclose(G, Li.T @ Li, rtol=0, atol=10 * n * EPS * np.abs(Li.T @ Li).max())
            w, Q = eigh(S)
            np.testing.assert_allclose(Q.T @ Q, np.eye(n), rtol=0, atol=100 * n * EPS)
            np.testing.assert_allclose((Q * w) @ Q.T, S, rtol=0, atol=100 * n * EPS * np.abs(S).max())
            # eigenvalues are perfectly conditioned (Weyl): within n eps |S| of numpy's
            np.testing.assert_allclose(w, np.linalg.eigvalsh(S), rtol=0, atol=100 * n * EPS * np.abs(w).max())
            np.testing.assert_allclose(inverse(M) @ M, np.eye(n), atol=1e-8 * np.linalg.cond(M))
    assert not cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]))[1]  # indefinite
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        inverse(np.array([[1.0, 2.0], [2.0, 4.0]]))
    assert cholesky(np.zeros((0, 0)))[0].shape == inverse(np.zeros((0, 0))).shape == (0, 0)


@pytest.mark.slow
def test_the_contact_steps_do_not_compile_numbas_error_formatting(tmp_path):
    """A cold compile of the implicit and symplectic contact step (a fresh interpreter, an
    empty numba cache) compiles no shape-error formatting (numba's str of ints and string
    concatenation: ~3.5 s of a first run, behind np.linalg.solve's copy-in), no
    ``np.flatnonzero`` and no ``np.concatenate``: the step is loops and a direct LAPACK call."""
    import os
    import subprocess
    import sys

    code = """
import numpy as np
from numba.core import event
names = []
class L(event.Listener):
    def on_start(self, ev):
        d = ev.data.get("dispatcher") if ev.data else None
        names.append(d.py_func.__qualname__ if d is not None else "?")
    def on_end(self, ev):
        pass
event.register("numba:compile", L())
from hailstorm.runtime.compiled import substep_contacts
one = np.ones(1)
for implicit in (True, False):
    substep_contacts(one, one, one, one, one, 1e-4, np.eye(1), np.eye(1), np.eye(1), implicit, True,
                     np.arange(1), one, 1e10, 1e-10)
print("\\n".join(names))
"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run([sys.executable, "-c", code], check=True, env=env, capture_output=True, text=True).stdout
    names = out.split()
    assert "substep_contacts" in names and "solve" in names
    bad = [n for n in names if "raise_with_shape_context" in n or "integer_str" in n or "flatnonzero" in n
           or "concatenate" in n]
    assert not bad, bad


def test_lapack_kernels_are_cached_on_disk(tmp_path):
    """The LAPACK calls reach SciPy's routines by symbol name, not by a baked-in address, so a
    kernel calling them is written to numba's disk cache (a ctypes function pointer would make it
    "uses dynamic globals": compiled again in every process) and a second process loads it."""
    import os
    import subprocess
    import sys

    code = ("import numpy as np\n"
            "from hailstorm.runtime.compiled.lapack import cholesky\n"
            "L, ok = cholesky(np.array([[4.0, 2.0], [2.0, 3.0]]))\n"
            "assert ok and abs(L[1, 1] - 2.0 ** 0.5) < 1e-15\n"
            "print(cholesky.stats.cache_hits and 'hit' or 'miss')\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    runs = [subprocess.run([sys.executable, "-W", "error::numba.NumbaWarning", "-c", code], check=True, env=env,
                           capture_output=True, text=True).stdout.split() for _ in range(2)]
    assert runs == [["miss"], ["hit"]]
    assert any(p.name.startswith("lapack.cholesky") and p.suffix == ".nbi" for p in tmp_path.rglob("*"))
