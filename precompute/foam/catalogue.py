"""The default pad's foam: a published hyperfoam fit of an open-cell polyurethane foam.

:data:`SILBER_THEN_VE_FOAM` -- the long-term (relaxed) two-term Ogden-Storåkers parameters of
the viscoelastic open-cell polyurethane bedding foam ("VE-foam") of

    G. Silber, C. Then, *Preventive Biomechanics: Optimizing Support Systems for the Human
    Body in the Lying and Sitting Position*, Springer (2013), section 4.2.1, Table 4.3
    ("Long-term material parameters of VE-foam material"; fitted to hemispherical-indenter
    force-displacement data, N = 2, with Drucker stability reported "for all strains" in
    uniaxial compression).

What is verified and what is not (read from a public excerpt of the book, not the book itself):

* ``mu_j`` [MPa] ``5.280146E-03, 1.042675E-03``; ``nu_j`` ``1.587915E-04, 2.855843E-03``: read as printed.
* ``alpha_j`` ``2.208547E?01, 2.669817E?01``: the excerpt lost the exponent's sign. ``+01`` is
  taken (22.09, 26.70): it gives the plateau of a flexible foam's compression curve (nominal
  stress 0.40 kPa at 5 %, 0.93 kPa at 40 %, 1.12 kPa at 50 %), and is stable in uniaxial
  compression at every strain, as the book reports; ``-01`` (0.22, 0.27) would give a stiffening
  curve without a plateau (1.5 kPa at 10 %, 16 kPa at 50 %), unlike any flexible foam. With
  ``+01`` the tangent's ellipticity fades (acoustic eigenvalue ~1e-10 mu0) past 68 % equibiaxial
  compression, so :data:`SILBER_THEN_VE_FOAM` is checked to -65 %.
* density: not in the excerpt read. 50 kg/m^3 is an **assumption** (viscoelastic PU bedding
  foams are sold at about 40-80 kg/m^3), to be replaced by the book's Table 4.1 value.
* small-strain moduli follow from the parameters (``E0`` 12.7 kPa, ``nu0`` 6e-4): a soft, relaxed
  foam. At impact rates a viscoelastic foam is much stiffer than its long-term fit: the
  long-term law is a lower bound on the pad's stiffness, not its impact response.

Mills & Gilchrist (Modelling the indentation of low density polymer foams, Cellular Polymers
19 (2000) 389) fitted the same energy to open-cell PU foams with ``nu = 0``; their numbers were
not available to verify here, so they are not used.

A firmer foam (a seat or saddle foam, ``E0`` of order 0.1-1 MPa, with its density from the same
source) was searched for and not found in a readable form: Silber & Then's Table 4.2 (their
high-resilience "HR" foam, fitted beside the VE foam), Petre, Erdemir & Cavanagh (Comput. Methods
Biomech. Biomed. Eng. 9 (2006) 231, insole foams), Briody et al. (Comput. Mater. Sci. 2012,
wheelchair seating foam), Kossa & Berezvai (Polym. Test. 2016) and Li et al. (BioResources 18
(2023) 7731, seat foundation foams) name such fits, but their tables were not in the excerpts at
hand. No parameter is entered without its table, so the VE foam stays the default. It is ~160
times softer than the linear seat's 2 MPa and has no densification to speak of (its volumetric
exponents ``alpha_i beta_i`` are 0.004 and 0.08): under terminal-speed hail the pad bottoms out
(measured: a 3.9 mm stone at its terminal 11.4 m/s on a 15 mm pad reaches 0.74 ``h`` at 2.1 N, where
:func:`~hailstorm.precompute.foam.impact.strike` stops with a NewtonError).
"""

from __future__ import annotations

from hailstorm.precompute.foam.material import Hyperfoam

__all__ = ["DEFAULT_FOAM", "SILBER_THEN_VE_FOAM"]

SILBER_THEN_VE_FOAM = Hyperfoam(
    mu=(5.280146e3, 1.042675e3),
    alpha=(22.08547, 26.69817),
    nu=(1.587915e-4, 2.855843e-3),
    density=50.0,
    name="silber-then-ve-foam",
    source=("Silber & Then, Preventive Biomechanics, Springer 2013, Table 4.3 (long-term VE-foam); "
            "alpha exponent sign inferred (+01); density 50 kg/m^3 assumed, not from the source"),
    check_range=(-0.65, 0.5),
)

#: the default pad's foam
DEFAULT_FOAM = SILBER_THEN_VE_FOAM
