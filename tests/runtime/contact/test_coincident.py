"""Near-coincident stones: two stones dropped on one spot.

The compliance W of two contacts at (nearly) the same point is (nearly) singular;
the storm takes its capacitance under the contact API's one policy (the
pseudo-inverse beyond ``COND_LIMIT``: the min-norm, symmetric split of the common
force) and damps every normal mode of it to the target restitution. Each stone
must then rebound like a single stone: finite, symmetric, e on target, on every
integrator.
"""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.driver import Storm

def _drop_pair(gf, integrator, d, patch, r=0.002, v0=5.0, dt=2e-4):
    """Two stones of radius ``r`` side by side ``d`` apart onto the flat plate at ``v0``:
    each stone's restitution (rebound / impact normal speed) and the storm."""
    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, dt=dt, integrator=integrator, restitution=0.5, patch=patch)
    st = Storm(gf, sc, spawn=False)
    c = np.array([0.0613, 0.0011, 0.0])  # inside a triangle, off its centre
    st.add_stones(np.array([c + [-d / 2, 0, r + 1e-3], c + [d / 2, 0, r + 1e-3]]), np.tile([0.0, 0.0, -v0], (2, 1)),
                  np.full(2, r))
    v_in: list = [None, None]
    v_out: list = [None, None]
    was = [False, False]
    for _ in range(int(0.02 / dt)):
        vb = st.vel[:, 2].copy()
        st.step()
        for i in range(2):
            now = bool(st.ctri[i] >= 0 or st.stones.offset[i] > 0)  # in contact, or in a patch's dead zone
            if now and not was[i] and v_in[i] is None:
                v_in[i] = -float(vb[i])
            if was[i] and not now and v_in[i] is not None and v_out[i] is None:
                v_out[i] = float(st.vel[i, 2])
            was[i] = now
        if None not in v_out:
            break
    assert None not in v_in and None not in v_out, f"no rebound: in {v_in}, out {v_out}"
    return np.array(v_out) / np.array(v_in), st


@pytest.mark.parametrize("integrator", ["implicit", "symplectic", "exact"])
@pytest.mark.parametrize("d", [0.0, 1e-9, 1e-5, 1e-3])
@pytest.mark.parametrize("patch", ["hertz", "none"])
def test_coincident_stones_rebound_with_the_target_restitution(gf, integrator, d, patch):
    e, st = _drop_pair(gf, integrator, d, patch)
    assert np.isfinite(st.pos).all() and np.isfinite(st.vel).all() and np.isfinite(st.u).all()
    assert np.all(np.abs(e - 0.5) < 0.1), e
    # symmetric: the two stones behave alike (exactly so when they share the point)
    assert abs(e[0] - e[1]) < (1e-6 if d <= 1e-9 else 0.05), e


def test_spd_inverse_is_the_contact_api_policy():
    """One policy: the storm's inverse (numpy and compiled) is the capacitance's
    factor -- the exact inverse of a well-conditioned W, the pseudo-inverse of a
    (nearly) singular one (coincident contacts: symmetric, finite)."""
    from hailstorm.runtime.compiled import inv_spd
    from hailstorm.runtime.contact.policy import COND_LIMIT, PINV_RCOND, spd_inverse

    W1 = np.array([[2.0, 0.5], [0.5, 1.0]])
    np.testing.assert_allclose(spd_inverse(W1), np.linalg.inv(W1), rtol=1e-12)
    for eps in (0.0, 1e-15, 1e-13):
        W = np.array([[1.0, 1.0 - eps], [1.0 - eps, 1.0]]) * 8e-5
        K = spd_inverse(W)
        assert np.isfinite(K).all()
        np.testing.assert_allclose(K, np.full((2, 2), 0.25 / 8e-5), rtol=1e-6)  # the min-norm split
        np.testing.assert_allclose(inv_spd(W, COND_LIMIT, PINV_RCOND), K, rtol=1e-9)


def test_modal_damping_damps_the_shared_mode_to_target():
    """Coincident contacts (pseudo-inverse K): the mode the two stones share gets the
    damping ratio of the target restitution, the free (zero) mode none; a single
    contact gets damping_coefficients' dashpot."""
    from hailstorm.runtime.storm.hail import damping_coefficients, damping_ratio_for_restitution, modal_damping

    m = np.array([3e-5, 3e-5])
    K = np.full((2, 2), 0.25 / 8e-5)
    C = modal_damping(K, m, 0.5, integrator="exact")
    u = np.array([1.0, 1.0]) / np.sqrt(2.0)
    w = np.sqrt(u @ K @ u / m[0])  # the shared mode's frequency
    assert u @ C @ u / (2.0 * m[0] * w) == pytest.approx(damping_ratio_for_restitution(0.5), rel=1e-9)
    assert abs(np.array([1.0, -1.0]) @ C @ np.array([1.0, -1.0])) < 1e-12 * np.abs(C).max()
    k1 = np.array([[4e3]])
    np.testing.assert_allclose(modal_damping(k1, m[:1], 0.5, dt=1e-5, integrator="implicit"),
                               np.diag(damping_coefficients(k1, m[:1], 0.5, dt=1e-5, integrator="implicit")),
                               rtol=1e-12)
