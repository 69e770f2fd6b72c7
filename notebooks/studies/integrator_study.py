"""What the storm reports, by integrator and step: ``max_contact_force`` and ``max_indentation_m``
of the default storm as the step is refined.

``exact`` (the default) integrates each contact set's sub-step in closed form: its peaks are
the model's own, the same at every ``dt``. ``implicit`` (backward Euler) and ``symplectic``
hold ``omega dt`` at ``omega_dt`` in their sub-steps whatever ``dt``, so their peaks move with
``omega_dt`` instead, at first order (``docs/how-it-works.md``, "Integrators")::

    python -m studies.integrator_study --out docs/_generated/integrator_study.txt

Each row is one storm (the default scene, its seed, on the default seat unless ``--gf``); the
last columns are the peaks' differences from the first row's (``exact`` at the default ``dt``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from studies import record

__all__ = ["ROWS", "main", "run_rows"]

#: (integrator, dt [s] or None for the scene's, omega_dt or None for the scene's), in the table's order
ROWS: tuple[tuple[str, float | None, float | None], ...] = (
    ("exact", None, None),
    ("exact", 5e-4, None),
    ("exact", 5e-5, None),
    ("implicit", None, 0.2),
    ("implicit", None, 0.1),
    ("implicit", None, 0.05),
    ("implicit", None, 0.02),
)


def run_rows(gf: Any, scene: Any, rows: tuple[tuple[str, float | None, float | None], ...] = ROWS) -> list[dict[str, Any]]:
    """Run ``scene`` once per row with its integrator, ``dt`` and ``omega_dt`` (None: the scene's).

    Returns
    -------
    list of dict
        Per row: ``integrator``, ``dt``, ``omega_dt``, ``stones_hit``, ``impacts``,
        ``max_contact_force`` [N], ``max_indentation_m``, ``substeps``, ``wall_s`` (the
        storm's own, :attr:`StormStats.wall_time_s`).
    """
    from hailstorm.runtime.storm import run_storm

    out = []
    for integrator, dt, omega_dt in rows:
        kw: dict[str, Any] = {"integrator": integrator}
        if dt is not None:
            kw["dt"] = dt
        if omega_dt is not None:
            kw["omega_dt"] = omega_dt
        sc = scene.with_(**kw)
        st = run_storm(gf, sc, progress=False, keep_frames=False).stats
        out.append({"integrator": integrator, "dt": sc.time.dt, "omega_dt": sc.time.omega_dt,
                    "stones_hit": st.stones_hit, "impacts": st.impacts, "max_contact_force": st.max_contact_force,
                    "max_indentation_m": st.max_indentation_m, "substeps": st.substeps, "wall_s": st.wall_time_s})
    return out


def table(rows: list[dict[str, Any]]) -> list[str]:
    """The rows as a Markdown table, with the peaks' differences from the first row."""
    F0, d0 = rows[0]["max_contact_force"], rows[0]["max_indentation_m"]
    lines = ["| integrator | dt [ms] | omega_dt | stones hit | impacts | max force [N] | max indentation [mm] "
             "| sub-steps | storm wall [s] | force vs row 1 | indentation vs row 1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        od = "-" if r["integrator"] == "exact" else f"{r['omega_dt']:g}"
        lines.append(f"| {r['integrator']} | {1e3 * r['dt']:g} | {od} | {r['stones_hit']} | {r['impacts']} "
                     f"| {r['max_contact_force']:.2f} | {1e3 * r['max_indentation_m']:.4f} | {r['substeps']:,} "
                     f"| {r['wall_s']:.2f} | {100 * (r['max_contact_force'] / F0 - 1):+.2f} % "
                     f"| {100 * (r['max_indentation_m'] / d0 - 1):+.2f} % |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studies.integrator_study", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", type=Path, default=None, help="a bundle (default: the default seat, built or cached)")
    ap.add_argument("--out", type=Path, default=None, help="also write the lines there (with their header)")
    args = ap.parse_args(argv)
    import hailstorm.runtime
    from hailstorm.runtime.storm.scene import Scene, SeatSettings
    from studies.resolution_study import seat_bundle

    stamp = record.stamp()
    gf = hailstorm.runtime.load(args.gf) if args.gf is not None else seat_bundle(SeatSettings.default().mesh_size)
    scene = Scene.default()
    t0 = time.perf_counter()
    lines = [f"# the default scene ({scene.storm.duration:g} s, seed {scene.storm.seed}) on "
             f"{'the default seat' if args.gf is None else args.gf.name}; one storm per row", "",
             *table(run_rows(gf, scene))]
    lines.append(f"# {time.perf_counter() - t0:.0f} s in all")
    print("\n".join(lines), flush=True)
    if args.out is not None:
        record.write_run(args.out, record.command("python -m studies.integrator_study", argv), stamp, lines)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
