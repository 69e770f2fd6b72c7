"""The storm's contact integrators: one contact step of a contact set, its dashpot,
and the sub-step size.

``integrator = "exact"`` solves the damped linear contact dynamics of the set in
closed form over the sub-step (:func:`hailstorm.runtime.compiled.exact_step`);
``"implicit"`` / ``"symplectic"`` take one backward / symplectic Euler step
(:func:`hailstorm.runtime.compiled.substep_contacts`) of a sub-step sized by
:meth:`ContactIntegrator.substep_size`. The dashpot damps every normal mode of
the set to the target restitution (:func:`hailstorm.runtime.storm.hail.modal_damping`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from hailstorm.runtime.contact import policy
from hailstorm.runtime.compiled import (
    exact_step,
    explicit_modes,
    modal_stiffness,
    substep_contacts,
    substep_damping,
    substep_size,
)
from hailstorm.runtime.storm.hail import X_GRID, Z_GRID, ContactStep, Integrator, contact_modes

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.contact_set import ContactSet
    from hailstorm.runtime.storm.scene_sections import ContactSettings, TimeSettings
    from hailstorm.runtime.storm.stones import Stones

__all__ = ["ContactIntegrator"]


class ContactIntegrator:
    """The scene's contact integrator for the storm's contact sets.

    Parameters
    ----------
    time : TimeSettings
        ``integrator``, ``adaptive``, ``omega_dt``, ``approach_fraction``,
        ``rest_speed``, ``dt``, ``max_substeps``.
    contact : ContactSettings
        ``restitution``, ``unilateral``, ``mode``.
    """

    def __init__(self, time: TimeSettings, contact: ContactSettings) -> None:
        self.kind = Integrator(time.integrator)
        self.name = str(self.kind)
        self.exact = self.kind.closed_form
        self.time = time
        self.contact = contact
        self.hmin = time.min_substep
        #: the sub-steps are sized (adaptive implicit / symplectic), by the triangles' stiffness among others
        self.sizes_substeps = time.adaptive and not self.exact
        #: the sub-steps' omega h target: symplectic Euler's explicit dashpot makes its peak force
        #: first order in omega h (-21 % at 0.2, -5 % at 0.05 on one impact), so it takes half the
        #: scene's (measured, default scene: max force 68.8 / 72.9 N at dt 0.05 / 0.5 ms with the
        #: full target, 71.93 / 71.89 N with half, for 30 % more sub-steps)
        self.omega_dt = float(time.omega_dt) * self.kind.omega_dt_factor
        self._none = np.zeros(0, dtype=np.int64)
        self._no_forces = np.zeros(0)
        self._no_e3 = np.zeros((0, 3))

    def step(self, cc: ContactSet, q: np.ndarray, vq: np.ndarray, a: np.ndarray, mq: np.ndarray, gq: np.ndarray,
             h: float, group: np.ndarray, wts: np.ndarray, always: np.ndarray) -> ContactStep:
        """One contact step of set ``cc`` over ``h`` in its constrained coordinates
        (:func:`hailstorm.runtime.compiled.contact_prep`), with unilateral release."""
        lim, rcond = float(policy.COND_LIMIT), float(policy.PINV_RCOND)
        if self.exact:
            C = self.exact_damping(cc, mq)
            qn, vn, act, force, seat, peak, pub = exact_step(q, vq, a, mq, gq, h, cc.K, cc.W, C, self.contact.unilateral,
                                                             group, wts, always, lim, rcond)
            return ContactStep(q=qn, v=vn, active=act, force=force, seat_force=seat, peak_seat_force=peak,
                               peak_ubar=pub)
        K, W, C = self.contact_matrices(cc, mq, h)
        qn, vn, act, force, seat = substep_contacts(q, vq, a, mq, gq, h, K, W, C, self.kind.backward_euler,
                                                    self.contact.unilateral, group, wts, lim, rcond)
        return ContactStep(q=qn, v=vn, active=act, force=force, seat_force=seat, peak_seat_force=seat,
                           peak_ubar=qn - a)

    @staticmethod
    def _modes(cc: ContactSet, mq: np.ndarray) -> tuple:
        """The contact set's normal modes (cached with the set, for the masses they were computed with;
        other masses drop the cached dashpot too)."""
        if cc.modes is None or cc.mode_masses is None or not np.array_equal(cc.mode_masses, mq):
            cc.modes = contact_modes(cc.K, mq)
            cc.mode_masses = np.array(mq, dtype=np.float64)
            cc.C = None
        return cc.modes

    def exact_damping(self, cc: ContactSet, mq: np.ndarray) -> np.ndarray:
        """Exact-integrator dashpot of a contact set, per mode (:func:`hailstorm.runtime.storm.hail.modal_damping`;
        cached with the set)."""
        om2, Phi, sqm = self._modes(cc, mq)  # (cached; a change of masses drops C)
        if cc.C is None or cc.C.shape != (mq.size, mq.size):
            cc.C = substep_damping(om2, Phi, sqm, self.contact.restitution, 0.0, False, X_GRID, Z_GRID)
        return cc.C

    def contact_matrices(self, cc: ContactSet, mq: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(K, W, C)`` of a sub-step ``h`` of the implicit or symplectic integrator.

        ``C`` is the dashpot per mode (:func:`hailstorm.runtime.storm.hail.modal_damping`: backward
        Euler's numerical damping compensated). For the symplectic (explicit) step, ``K``
        and ``W`` carry the modes it can resolve (:func:`hailstorm.runtime.compiled.modal.explicit_modes_py`:
        unchanged at ``omega h`` <~ 0.3, at most ``1 / h^2``); the implicit step takes the
        set's own.
        """
        om2, Phi, sqm = self._modes(cc, mq)
        K, W = cc.K, cc.W
        if self.kind.explicit:
            om2 = explicit_modes(om2, float(h))
            K, W = modal_stiffness(om2, Phi, sqm)
        C = substep_damping(om2, Phi, sqm, self.contact.restitution, float(h), self.kind.backward_euler, X_GRID, Z_GRID)
        return K, W, C

    def substep_size(self, stones: Stones, near: np.ndarray, h_left: float, cc: ContactSet | None,
                     k_tri: np.ndarray | None, g: np.ndarray) -> float:
        """The next sub-step of the near stones, at most ``h_left`` (adaptive
        ``"implicit"``/``"symplectic"``: approach and ``omega h`` limits; see
        :func:`hailstorm.runtime.compiled.substep_size`; ``k_tri``: the triangles'
        point stiffness)."""
        if not self.sizes_substeps or k_tri is None:
            return h_left  # exact: no stability/accuracy limit; impacts are caught by time of impact
        if cc is not None and cc.stones.size:
            cs, kd, cn, cx, cr = cc.stones, cc.Kdiag, cc.normals, cc.X, cc.rest - stones.shift[cc.stones]
        else:
            cs, kd, cn, cx, cr = self._none, self._no_forces, self._no_e3, self._no_e3, self._no_forces
        return float(substep_size(near, float(h_left), float(self.hmin), stones.vel, stones.radius, stones.mass,
                                  stones.pos, stones.gap, stones.near_tri, stones.ctri, k_tri,
                                  self.time.approach_fraction, self.time.rest_speed, self.omega_dt,
                                  self.kind.explicit, cs, kd, self.contact.sticky, cn, cx, cr, g))

    def warm_up(self, stones: Stones, k_tri: np.ndarray | None, g: np.ndarray, dt: float) -> None:
        """Load (or compile) the integrator's kernels with the storm loop's argument types."""
        one = np.ones(1)
        if self.exact:
            exact_step(one, one, one, one, one, 1e-4, np.eye(1), np.eye(1), np.eye(1), True, np.arange(1), one,
                       np.zeros(1, dtype=bool), 1e10, 1e-10)
            # its dashpot (formerly compiled silently at the first contact)
            substep_damping(one, np.eye(1), one, 0.5, 0.0, False, X_GRID, Z_GRID)
            return
        substep_contacts(one, one, one, one, one, 1e-4, np.eye(1), np.eye(1), np.eye(1), True, True,
                         np.arange(1), one, 1e10, 1e-10)
        substep_damping(one, np.eye(1), one, 0.5, 1e-4, True, X_GRID, Z_GRID)
        if self.sizes_substeps and k_tri is not None:
            self.substep_size(stones, np.zeros(0, dtype=np.intp), dt, None, k_tri, g)
