"""The default seat's frontier with the new routes: the near field and a compressed D beside the dense one.

For each surface size (P2, hat columns, the half-space near field: the default seat's settings but
the size), one row per storage (dense, and compressed with ``--tol``):

* **error**: the force at Hertz's depth of stones of 2.5, 5 and 12.5 mm at rest and at the peak of an
  impact at terminal speed, at the rear, middle and nose, on a vertex, an edge and a centroid
  (:func:`studies.resolution_study.seat_table`), against the finest size's dense bundle:
  the largest and the median |error| over the 54 cases, and the largest over the stones a storm
  mostly has (2.5 and 5 mm);
* **precompute**: the bundle's recorded mesh + assembly + solve seconds, and the compression's;
* **stored**: the bytes of D as stored (dense, or the H-matrix);
* **runtime**: a fresh contact solve of 100 random point contacts with the surface's displacement
  (``solve_contacts``, min/median/max of repeated calls), and a short storm's real-time factor
  (the default scene over ``--duration``, min/median/max of ``--repeat`` runs; higher is faster).

Bundles are built (or read from the cache) as the default seat is: ``--sizes`` in mm, the last the
reference. Run ``python -m studies.routes_study [--sizes 6,4,3] [--tol 1e-2] [--out FILE]
[--plot PNG]`` (:func:`plot_frontier` draws the table as a chart).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from studies import record

__all__ = ["format_rows", "main", "plot_frontier", "route_rows", "solve_times", "storm_rtf"]


def solve_times(gf: Any, contacts: int = 100, repeat: int = 20, seed: int = 0) -> list[float]:
    """Wall seconds of ``solve_contacts`` (frictionless, bilateral, surface displacement on every vertex)
    for ``contacts`` random point contacts on contactable triangles, ``repeat`` calls (the first one
    excluded: it compiles)."""
    from hailstorm.runtime.contact.solve import solve_contacts

    rng = np.random.default_rng(seed)
    ok = np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))
    tri = rng.choice(ok, size=contacts, replace=False)
    bary = rng.dirichlet(np.ones(3), size=contacts)
    ubar = np.zeros((contacts, 3))
    ubar[:, 2] = -1e-4
    times = []
    for _ in range(repeat + 1):
        t = time.perf_counter()
        solve_contacts(gf, tri, bary, ubar, mode="frictionless")
        times.append(time.perf_counter() - t)
    return times[1:]


def storm_rtf(gf: Any, duration: float, repeat: int) -> list[float]:
    """Real-time factors (simulated over wall time) of the default scene over ``duration`` on ``gf``,
    ``repeat`` runs after one that is not counted (it loads the compiled kernels and warms the caches)."""
    from hailstorm.runtime import run_storm
    from hailstorm.runtime.storm.scene import Scene

    scene = Scene.default().with_(duration=duration)
    out = []
    for _ in range(repeat + 1):
        t = time.perf_counter()
        run_storm(gf, scene, progress=False, keep_frames=False)
        out.append(duration / (time.perf_counter() - t))
    return out[1:]


def _errors(gf: Any, ref: Any) -> dict[str, float]:
    from studies.resolution_study import DEFAULT_MODEL, SITES, seat_table

    rows = seat_table(gf, ref, near_field=DEFAULT_MODEL)
    err = np.array([[abs(r[s]) for s in SITES] for r in rows])
    small = np.array([r["R_mm"] < 6 for r in rows])
    return {"max": float(err.max()), "median": float(np.median(err)), "small": float(err[small].max())}


def route_rows(sizes: Sequence[float], tol: float, duration: float, repeat: int) -> list[dict[str, Any]]:
    """One row per size and storage (see the module notes); the last size is the reference."""
    from hailstorm.precompute.hmatrix import compress_bundle
    from hailstorm.runtime import load

    from studies.resolution_study import seat_bundle

    gfs = [seat_bundle(h, progress=True) for h in sizes]
    ref = gfs[-1]
    rows = []
    for h, gf in zip(sizes, gfs):
        t = gf.manifest.get("timings_s", {})
        pre = sum(float(t.get(k, 0.0)) for k in ("mesh", "assemble", "solve"))
        err = _errors(gf, ref) if gf is not ref else None
        dense = {"size_mm": h * 1e3, "storage": "dense", "columns": gf.D.shape[1], "err": err,
                 "precompute_s": pre, "compress_s": 0.0, "stored_MiB": gf.D.nbytes / 2**20,
                 "solve_ms": [1e3 * x for x in solve_times(gf)], "rtf": storm_rtf(gf, duration, repeat)}
        rows.append(dense)
        with tempfile.TemporaryDirectory(dir=Path(gf.path).parent) as tmp:
            t0 = time.perf_counter()
            hgf = load(compress_bundle(gf.path, Path(tmp) / "h", tol))
            seconds = time.perf_counter() - t0
            comp = hgf.manifest["compliance"]
            herr = _errors(hgf, ref)
            rows.append({"size_mm": h * 1e3, "storage": f"H {tol:g}", "columns": gf.D.shape[1], "err": herr,
                         "precompute_s": pre, "compress_s": seconds, "stored_MiB": comp["stored_bytes"] / 2**20,
                         "col_err": comp["error"]["max"],
                         "solve_ms": [1e3 * x for x in solve_times(hgf)], "rtf": storm_rtf(hgf, duration, repeat)})
            del hgf
    return rows


def format_rows(rows: Sequence[dict[str, Any]]) -> list[str]:
    out = ["| size mm | D stored as | columns | force error max % | median % | 2.5-5 mm stones max % | "
           "precompute s | + compress s | stored MiB | s=100 solve ms min/med/max | storm RTF min/med/max |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        e = r["err"]
        errs = ("reference", "", "") if e is None else (f"{100 * e['max']:.1f}", f"{100 * e['median']:.1f}",
                                                          f"{100 * e['small']:.1f}")
        out.append(f"| {r['size_mm']:g} | {r['storage']} | {r['columns']} | {errs[0]} | {errs[1]} | {errs[2]} | "
                   f"{r['precompute_s']:.1f} | {r['compress_s']:.1f} | {r['stored_MiB']:.1f} | "
                   f"{record.min_median_max(r['solve_ms'], '.1f')} | {record.min_median_max(r['rtf'], '.2f')} |")
    return out


def plot_frontier(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """The frontier chart of :func:`route_rows`: the largest force error against the finest size
    (and, hollow, the median) over what each route costs -- precompute seconds (with the
    compression), stored MiB of D and a fresh 100-contact solve (median ms) -- one marker per size
    and storage (the reference, without an error, left out). Written to ``path``; returns it."""
    import os

    import matplotlib

    if "MPLBACKEND" not in os.environ:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import LogLocator, NullFormatter, StrMethodFormatter

    shown = [r for r in rows if r["err"] is not None]
    if not shown:
        raise ValueError("plot_frontier needs a row with an error (a size other than the reference)")
    costs = (("precompute + compression [s]", lambda r: r["precompute_s"] + r["compress_s"]),
             ("D stored [MiB]", lambda r: r["stored_MiB"]),
             ("fresh solve, 100 contacts + surface [ms, median]", lambda r: float(np.median(r["solve_ms"]))))
    fig, axes = plt.subplots(1, 3, figsize=(11.0, 3.8), sharey=True, layout="constrained")
    for ax, (label, cost) in zip(axes, costs):
        for r in shown:
            dense = r["storage"] == "dense"
            colour = "#377eb8" if dense else "#e41a1c"
            x = cost(r)
            ax.scatter([x], [100 * r["err"]["max"]], marker="o" if dense else "s", s=45, color=colour, zorder=3)
            ax.scatter([x], [100 * r["err"]["median"]], marker="o" if dense else "s", s=45, facecolors="none",
                       edgecolors=colour, zorder=3)
            ax.annotate(f"{r['size_mm']:g} mm", (x, 100 * r["err"]["max"]), textcoords="offset points",
                        xytext=(5, 5) if dense or r["err"]["max"] < 0.005 else (5, -11), fontsize=7.5, color=colour)
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(label)
        ax.grid(True, which="both", lw=0.3, alpha=0.5)
    axes[0].axhline(2.0, color="0.4", lw=0.8, ls="--")
    axes[0].axhline(5.0, color="0.4", lw=0.8, ls=":")
    for ax in axes[1:]:
        ax.axhline(2.0, color="0.4", lw=0.8, ls="--")
        ax.axhline(5.0, color="0.4", lw=0.8, ls=":")
    axes[0].set_ylabel("force error against the finest size [%]")
    axes[0].set_ylim(-0.3, max(6.0, 1.15 * 100 * max(r["err"]["max"] for r in shown)))
    handles = [plt.Line2D([], [], ls="", marker="o", color="#377eb8", label="dense D"),
               plt.Line2D([], [], ls="", marker="s", color="#e41a1c", label="compressed D (--tol)"),
               plt.Line2D([], [], ls="", marker="o", mfc="none", mec="0.3", label="hollow: median over the 54 cases"),
               plt.Line2D([], [], color="0.4", lw=0.8, ls="--", label="2 % target"),
               plt.Line2D([], [], color="0.4", lw=0.8, ls=":", label="5 % must")]
    fig.legend(handles=handles, fontsize=7.5, loc="outside lower center", ncol=5, frameon=False)
    fig.suptitle("The default seat's frontier: stone force at a given depth (54 cases, near field on) "
                 "against what each route costs", fontsize=9)
    return record.save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studies.routes_study", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="6,4,3", help="surface sizes in mm, the last the reference (default 6,4,3)")
    ap.add_argument("--tol", type=float, default=1e-2, help="the compressed rows' --tol (default 1e-2)")
    ap.add_argument("--duration", type=float, default=0.2, help="simulated seconds of each storm (default 0.2, "
                    "the default storm's)")
    ap.add_argument("--repeat", type=int, default=3, help="storms per row (default 3)")
    ap.add_argument("--out", type=Path, default=None, help="also write the table there (with its header)")
    ap.add_argument("--plot", type=Path, default=None, help="also draw the frontier chart there (plot_frontier)")
    args = ap.parse_args(argv)
    stamp = record.stamp()
    sizes = [float(x) * 1e-3 for x in args.sizes.split(",")]
    rows = route_rows(sizes, args.tol, args.duration, args.repeat)
    lines = format_rows(rows)
    lines += ["", f"force error: 54 cases (stones of 2.5, 5, 12.5 mm at rest and at the peak of an impact at "
              f"terminal speed; rear, middle, nose; vertex, edge, centroid) against the {args.sizes.split(',')[-1]} "
              "mm dense bundle, with the near field; precompute: the bundle's mesh + assembly + solve seconds as "
              f"recorded; storm: the default scene over {args.duration:g} s"]
    print("\n".join(lines))
    if args.out:
        record.write_run(args.out, record.command("python -m studies.routes_study", argv), stamp, lines)
    if args.plot:
        print(f"chart: {plot_frontier(rows, args.plot)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
