"""studies.integrator_study on the synthetic plate and a short storm."""

from __future__ import annotations

from helpers import plate_gf

from hailstorm.runtime.storm.scene import Scene
from studies import integrator_study


def test_rows_follow_the_settings_and_exact_peaks_do_not_move_with_dt():
    """Each row runs with its integrator, dt and omega_dt; the exact integrator's peaks are the same at
    dt 0.5 and 0.05 ms (its sub-steps are closed-form: only the contact sets' timing moves with dt,
    1e-3 relative is ample; measured here: equal to 4 digits, on the default storm 4e-5), the implicit one's are not
    (first order in omega_dt: +29 % here); the table has a line per row with the first row at +0.00 %.
    On the flat plate (``helpers.plate_gf``): no edge of a faceted surface under a sliding stone."""
    gf = plate_gf()
    scene = Scene.from_flat(duration=0.05, stones=10, seed=1, r_min=0.003, r_max=0.006)
    rows = integrator_study.run_rows(gf, scene, (("exact", 5e-4, None), ("exact", 5e-5, None),
                                                 ("implicit", 5e-4, 0.2)))
    assert [(r["integrator"], r["dt"], r["omega_dt"]) for r in rows] == [
        ("exact", 5e-4, scene.time.omega_dt), ("exact", 5e-5, scene.time.omega_dt), ("implicit", 5e-4, 0.2)]
    assert all(r["impacts"] > 0 and r["max_contact_force"] > 0 for r in rows)
    e1, e2, im = rows
    assert abs(e2["max_contact_force"] / e1["max_contact_force"] - 1) < 1e-3
    assert abs(e2["max_indentation_m"] / e1["max_indentation_m"] - 1) < 1e-3
    assert abs(im["max_contact_force"] / e1["max_contact_force"] - 1) > 1e-2
    lines = integrator_study.table(rows)
    assert len(lines) == 2 + 3 and lines[2].endswith("| +0.00 % | +0.00 % |")
