"""The studies behind the evidence (``studies``): the code the notebooks next to it run.

* :mod:`studies.study` - speed against accuracy of the Green's functions
  (mesh size, element order, load type, solver, storage);
* :mod:`studies.contact_study` - mesh dependence of contact stiffness,
  stability of the integrators, degenerate contacts, P1 locking.
* :mod:`studies.hertz_study` - patch contacts against Hertz on a graded
  half-space block: force-indentation, a stone at rest, a stone's impact.
* :mod:`studies.record` - the header (command, date, commit, load) and the
  atomic write of a measurement the documentation includes.

They use both stages (:mod:`hailstorm.precompute`, :mod:`hailstorm.runtime`);
neither stage imports them.
"""
