"""The ``hailstorm`` command line.

``hailstorm``                      run the default storm on the default seat
``hailstorm storm [options]``      run a storm (bundle built and cached on first use)
``hailstorm precompute [options]`` compute a Green's-function bundle
``hailstorm info DIR``             describe and verify a bundle
``hailstorm view OUT [--serve]``   the storm in OUT as one HTML page (served on localhost)

All printing and exit codes live here; the library raises exceptions.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

EXIT_USAGE = 2
EXIT_INPUT = 3
COMMANDS = ("precompute", "storm", "info", "view")


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0 or value != value or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def _parser() -> argparse.ArgumentParser:
    from hailstorm.precompute.fem import DEFAULT_POISSON, DEFAULT_YOUNG  # noqa: PLC0415 (cheap module)
    from hailstorm.precompute.greens import SOLVER_SPECS

    p = argparse.ArgumentParser(
        prog="hailstorm",
        description="A hail storm on a bicycle seat: point contacts on a linear elastic solid "
        "through precomputed Green's functions. With no command, runs the default storm.",
        epilog="With no command, `hailstorm [storm options]` runs the storm: for example "
        "`hailstorm -q --no-video --duration 1` (-q: no progress bars, info messages or numbers, "
        "warnings in one line; --no-video: no animation). Every storm option: hailstorm storm --help.",
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars, info messages or printed numbers; warnings in one line")
    sub = p.add_subparsers(dest="command")

    pre = sub.add_parser("precompute", parents=[common], help="compute a Green's-function bundle for a seat")
    from hailstorm.runtime.seat_settings import SeatSettings

    seat = SeatSettings.default()
    pre.add_argument("--mesh-size", type=_positive_float, default=seat.mesh_size,
                     help=f"element size on the hail-facing surface in metres (default {seat.mesh_size}: the "
                     "default seat's)")
    pre.add_argument("--order", type=int, choices=(1, 2), default=seat.order,
                     help=f"P1 or P2 tetrahedra (default {seat.order}: the default seat's, chosen by measured accuracy)")
    pre.add_argument("--volume-size", type=_positive_float, default=None, metavar="H",
                     help="volume grading of a meshed geometry: tetrahedra inside the body at most H metres "
                     "(at most --mesh-size) under the same surface mesh; D and the runtime's cost stay the same")
    pre.add_argument("--coarsening", type=_float, default=seat.coarsening, metavar="C",
                     help="elements of a meshed geometry grow to C times --mesh-size away from the hail-facing "
                     f"surface (default {seat.coarsening:g}: the default seat's; at least 1); a larger C keeps the "
                     "surface mesh and cuts the volume's vertices, the factor and the precompute's time on a thin pad")
    pre.add_argument("--young", type=_float, default=None,
                     help=f"Young's modulus in Pa of a one-material body (default {DEFAULT_YOUNG:g})")
    pre.add_argument("--poisson", type=_float, default=None,
                     help=f"Poisson's ratio of a one-material body (default {DEFAULT_POISSON})")
    pre.add_argument("--material", action="append", default=[], metavar="NAME=E,nu",
                     help="material of the volume group NAME (a gmsh Physical Volume): Young's modulus E in Pa "
                     "and Poisson's ratio nu, e.g. pad=0.5e6,0.3; repeat for each volume (instead of --young/--poisson)")
    pre.add_argument("--geometry", type=Path, default=None,
                     help="geometry (.geo/.step/.brep) or tetrahedral mesh (any meshio format) with "
                     "surface groups 'top' and 'clamp' (default: the built-in saddle)")
    pre.add_argument("--solver", choices=tuple(SOLVER_SPECS), default=next(iter(SOLVER_SPECS)),
                     help="sparse Cholesky with solves pruned for unit loads read at the surface (default), "
                     "CHOLMOD's general solve, SuperLU, or AMG-preconditioned CG for huge meshes")
    pre.add_argument("--amg-tol", type=_positive_float, default=1e-10, help="relative residual of the AMG solver")
    pre.add_argument("--tol", type=_float, default=None, metavar="T",
                     help="store D compressed (an H-matrix, format 3) whose columns are within relative error T "
                     "of the exact ones on 200 exact columns drawn at random (1e-12 to 0.1; the error is shown by "
                     "`hailstorm info`); default: D dense")
    pre.add_argument("--stream", action="store_true",
                     help="with --tol: compress D as its columns are solved, never holding it whole (for surfaces "
                     "whose dense D would not fit; an interrupted run resumes from its checkpoint)")
    pre.add_argument("--load", choices=("point", "hat"), default=seat.load,
                     help="a column of D responds to a unit nodal force (point, the default) or to one newton "
                     "spread over the vertex's hat function (hat: the consistent choice for --order 2)")
    pre.add_argument("--out", type=Path, required=True, help="bundle directory to write")
    pre.add_argument("--force", action="store_true", help="recompute even if --out holds an up-to-date bundle")
    pre.add_argument("--allow-large", action="store_true",
                     help="run even if the estimated memory (the solver and a few blocks of D) exceeds the memory "
                     "available, or D the free disk")
    pre.add_argument("--dtype", choices=("float64", "float32"), default="float64",
                     help="storage type of D (default float64; float32 halves D on disk and in the runtime, "
                     "each entry rounded by at most 2^-24 of itself; solved in float64 either way)")
    where = pre.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                       help="solve the column blocks of D on a local Dask cluster of N processes "
                       "(needs the 'dask' extra; default: in this process, fastest for small meshes)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="solve the column blocks on the running Dask cluster at ADDRESS "
                       "(e.g. tcp://head:8786; every worker needs hailstorm installed)")

    storm = sub.add_parser("storm", parents=[common], help="run a hail storm and write an animation, a ParaView series and summary.json")
    _storm_args(storm)

    info = sub.add_parser("info", parents=[common], help="describe and verify a bundle")
    info.add_argument("bundle", type=Path, help="a bundle directory (written by hailstorm precompute)")
    _view_args(sub.add_parser("view", parents=[common], help="the storm as one HTML page (--serve: on localhost)"))
    return p


def _view_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", type=Path, help="a storm's output folder (hailstorm storm --out)")
    p.add_argument("-o", "--output", type=Path, default=None, metavar="HTML",
                   help="the page to write (default OUT/viewer.html, listed in the storm's manifest)")
    p.add_argument("--stride", type=_positive_int, default=None, metavar="N",
                   help="hold every N-th frame (default: every frame while the page stays under about 20 MB; "
                        "a longer storm is subsampled and the page says by what stride)")
    p.add_argument("--serve", action="store_true", help="then serve the page on http://127.0.0.1:PORT/ until Ctrl-C")
    p.add_argument("--port", type=int, default=8000, help="the port of --serve (default 8000; 0: any free port)")


def _run_view(args: argparse.Namespace) -> int:
    """``hailstorm view``: write the storm's page, then (--serve) serve it on localhost."""
    from hailstorm.runtime.output.viewer import ViewerInputError, serve, write_page

    info = write_page(args.out, args.output, stride=args.stride)
    if not args.quiet:
        held = f"{info.frames} frames" if info.stride == 1 else \
            f"{info.frames} of {info.frames_total} frames (every {info.stride}th)"
        print(f"viewer   {info.path} ({info.bytes / 1e6:.1f} MB: {held}, {info.impacts} impacts)")
    if not args.serve:
        return 0

    def ready(url: str) -> None:
        print(f"serving  {url} (Ctrl-C stops)", flush=True)

    try:
        serve(info.path, port=args.port, ready=ready)
    except KeyboardInterrupt:
        return 0
    except OSError as exc:
        raise ViewerInputError(f"cannot serve on 127.0.0.1:{args.port}: {exc.strerror or exc} "
                               "(choose another --port)") from None
    return 0


def _storm_args(p: argparse.ArgumentParser) -> None:
    from hailstorm.runtime.storm.scene import Scene  # noqa: PLC0415 (the packaged default scene, for the help texts)
    from hailstorm.runtime.storm.hail import INTEGRATORS
    from hailstorm.runtime.output.storm_output import SERIES_FORMATS

    d = Scene.default()
    p.add_argument("--duration", type=_positive_float, default=None,
                   help=f"simulated time in seconds (default: the scene's, {d.storm.duration:g})")
    p.add_argument("--stones", type=int, default=None,
                   help=f"number of hailstones (default: the scene's rate, {d.storm.rate:g} per second, over the duration)")
    p.add_argument("--seed", type=int, default=None,
                   help=f"random seed; runs are reproducible from it (default: the scene's, {d.storm.seed})")
    p.add_argument("--integrator", choices=INTEGRATORS, default=None,
                   help=f"time integrator of the contacts (default: the scene's, {d.time.integrator})")
    p.add_argument("--dt", type=_positive_float, default=None, help=f"time step in seconds (default: the scene's, {d.time.dt:g})")
    p.add_argument("--gf", type=Path, default=None, help="bundle directory (default: build/cache the default seat)")
    p.add_argument("--scene", type=Path, default=None, help="TOML scene file holding every storm setting")
    p.add_argument("--out", type=Path, default=Path("hailstorm-out"), help="output directory (default ./hailstorm-out)")
    p.add_argument("--no-video", action="store_true", help="skip the animation")
    p.add_argument("--video-style", choices=("auto", "3d", "2d"), default="auto",
                   help="storm.mp4 in 3-D (VTK off-screen; auto: where it can be drawn, else 2-D) or the 2-D map "
                        "from above")
    p.add_argument("--video-dents", choices=("now", "peak"), default="now",
                   help="the 3-D video's seat at each frame's instant (now) or its largest displacement since the "
                        "previous frame (peak)")
    p.add_argument("--series", choices=SERIES_FORMATS, default=None,
                   help="the ParaView time series: one storm.vtkhdf (VTK >= 9.4, ParaView >= 5.13; default when "
                        "h5py is installed) or storm.pvd with two .vtu files per frame (older readers)")
    p.add_argument("--allow-large", action="store_true",
                   help="run a storm whose estimate exceeds the machine (memory, more than 10 million steps, "
                        "or an estimated hour of stepping)")


def _run_precompute(args: argparse.Namespace) -> int:
    from hailstorm.runtime.resources import require_extras

    require_extras("precompute", "hailstorm precompute")
    if args.workers is not None or args.scheduler is not None:
        require_extras("dask", "hailstorm precompute --workers/--scheduler")
    from hailstorm.precompute.pipeline import build_bundle
    from hailstorm.runtime.bundle.format import BundleError

    from hailstorm.precompute.materials import parse_material

    t0 = time.perf_counter()
    materials: dict[str, tuple[float, float]] = {}
    for text in args.material:
        name, young, poisson = parse_material(text)
        if name in materials:
            raise ValueError(f"--material {text!r}: volume {name!r} was already given a material")
        materials[name] = (young, poisson)
    try:
        path = build_bundle(
            args.out, geometry=args.geometry, mesh_size=args.mesh_size, order=args.order,
            volume_size=args.volume_size, coarsening=args.coarsening,
            young=args.young, poisson=args.poisson, materials=materials or None,
            solver=args.solver, tol=args.amg_tol, load=args.load, compress_tol=args.tol, stream=args.stream,
            reuse=not args.force, progress=not args.quiet, allow_large=args.allow_large,
            workers=args.workers, scheduler=args.scheduler, dtype=args.dtype,
        )
    except OSError as exc:  # what the library did not already name (a full disk...): still the user's
        raise BundleError(f"precompute failed: {_os_error(exc, args.out)}") from exc
    _print_bundle(path, rehash=False)  # just written and hashed: D is not read again
    if not args.quiet:
        print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def _run_info(args: argparse.Namespace) -> int:
    """``hailstorm info``: describe and verify a bundle; a reader that stops early (``| head``) is no error."""
    try:
        _print_bundle(args.bundle)
        sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()  # the reader went away: silence the interpreter's final flush too
    return 0


def _print_bundle(path: Path, rehash: bool = True) -> None:
    from hailstorm.runtime.bundle.read import load
    from hailstorm.runtime.bundle.format import array_specs

    gf = load(path, rehash=rehash)  # verifies: manifest hash and structure, array sizes and hashes, finite D, consistency
    m = gf.manifest
    mesh = m.get("mesh", {})
    print(f"bundle   {path}")
    print(f"key      {m['key'][:16]}  (format {m['format_version']}, hailstorm {m.get('code_version')})")
    print(f"mesh     {mesh.get('source')}: {mesh.get('n_points')} nodes, {mesh.get('n_tets')} tets, "
          f"P{gf.order}, {mesh.get('n_dofs')} dofs")
    print(f"surface  {gf.n_vertices} vertices, {len(gf.triangles)} triangles, "
          f"{int(gf.contactable.sum())} contactable, {int(gf.fixed.sum())} clamped")
    print(f"material E = {gf.young:g} Pa, nu = {gf.poisson:g}" + (" (under the contactable surface)"
                                                                   if len(m.get("materials") or ()) > 1 else ""))
    for mat in m.get("materials") or ():
        if len(m["materials"]) > 1:
            start, stop = mat["tets"]
            print(f"  volume {mat['volume']}: E = {mat['young']:g} Pa, nu = {mat['poisson']:g}, {stop - start} tets")
    if gf.hmatrix is None:
        print(f"D        {gf.D.shape[0]} x {gf.D.shape[1]} {gf.dtype} ({gf.D.nbytes / 2**20:.1f} MiB)")
    else:
        comp = m["compliance"]
        err = comp["error"]
        print(f"D        {gf.hmatrix.shape[0]} x {gf.hmatrix.shape[1]} as an H-matrix: {comp['stored_bytes'] / 2**20:.1f} MiB stored "
              f"of {comp['dense_bytes'] / 2**20:.1f} MiB dense ({comp['dense_bytes'] / max(comp['stored_bytes'], 1):.1f}x "
              f"smaller); {comp['far_blocks']} low-rank blocks of {comp['blocks']}, ranks up to {comp['max_rank']}")
        print(f"error    tol {comp['tol']:g}: measured against {err['columns']} exact columns drawn at random, "
              f"max {err['max']:.2e}, median {err['median']:.2e} (relative, per column)")
        expansion = gf.hmatrix.shape[0] * gf.hmatrix.shape[1] * gf.dtype.itemsize
        how = "from the H-matrix, never expanding D" if gf.reads_hmatrix else "from D expanded once into the cache"
        print(f"runtime  the storm and the contact API read it {how} (the {gf.dtype} expansion: "
              f"{expansion / 2**20:.1f} MiB; load(..., expand=) chooses)")
    t = m.get("timings_s", {})
    if t:
        print("timings  " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()))
    print(f"verified manifest hash and structure; {len(array_specs(m['format_version']))} arrays: sizes, SHA-256, "
          "shapes, dtypes; "
          "D finite; arrays consistent")


def _run_storm(args: argparse.Namespace) -> int:
    from hailstorm.runtime.bundle.read import load
    from hailstorm.runtime.output.storm_output import StormOutput, check_storm_out
    from hailstorm.runtime.resources import missing_module, require_extras
    from hailstorm.runtime.seat_settings import SeatSettings
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.run import run_storm
    from hailstorm.runtime.storm.estimate import hit_fraction

    overrides: dict[str, dict[str, Any]] = {}
    for section, options in (("storm", ("duration", "stones", "seed")), ("time", ("integrator", "dt"))):
        for k in options:
            if getattr(args, k) is not None:
                overrides.setdefault(section, {})[k] = getattr(args, k)
    if args.scene is not None:  # the file and the options checked together (a dt = 1 file with --duration 2)
        scene = Scene.from_toml(args.scene, overrides=overrides)
    else:
        scene = Scene.default()
        if overrides:
            data = scene.to_dict()
            for section, body in overrides.items():
                data[section].update(body)
            scene = Scene.from_dict(data, source="command line")
    # everything that can be refused cheaply, before the bundle and the storm
    # the default seat's precompute settings: the scene file's [seat], not part of the scene
    seat = SeatSettings.from_toml(args.scene) if args.scene is not None else SeatSettings.default()
    scene.estimate().check(allow_large=args.allow_large)
    if args.gf is None:
        require_extras("precompute", "the storm without --gf (it meshes the default seat to find its bundle)",
                       hint="(or run a bundle you have: hailstorm storm --gf DIR)")
    video = not args.no_video
    if video and (missing := missing_module("video")) is not None:
        video = False
        if not args.quiet:
            print(f"note: no animation ({missing} is not installed): pip install 'hailstorm[video]' for storm.mp4, "
                  "or --no-video", file=sys.stderr)
    series = args.series
    if series is None and (missing := missing_module("series")) is not None:
        series = "vtu"
        if not args.quiet:
            print(f"note: the ParaView series as .vtu files per frame ({missing} is not installed): "
                  "pip install 'hailstorm[series]' for one storm.vtkhdf", file=sys.stderr)
    out = args.out
    check_storm_out(out)
    if args.gf is not None:
        gf_path = args.gf
    else:
        from hailstorm.precompute.pipeline import build_bundle

        if not args.quiet:
            print(f"default seat: building or reusing the cached bundle (mesh size {seat.mesh_size} m)...")
        gf_path = build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                               volume_size=seat.volume_size, coarsening=seat.coarsening, young=seat.young,
                               poisson=seat.poisson, progress=not args.quiet)
    gf = load(gf_path)
    if args.gf is not None:
        _warn_seat_ignored(args, seat, gf)
    estimate = scene.estimate(gf.n_vertices, hit_fraction=hit_fraction(gf.vertices, gf.triangles, scene.storm.margin),
                              video=video, startup=True, series=series or "vtkhdf")  # run_storm checks and logs it
    with StormOutput(out, gf, video=video, disk_bytes=estimate.disk_bytes,
                     progress=not args.quiet, series=series,
                     video_options={"style": args.video_style, "dents": args.video_dents}) as sink:

        def add(frame: Any) -> None:
            _honour_signal()
            sink.add(frame)

        result = run_storm(gf, scene, progress=not args.quiet, on_frame=add, allow_large=args.allow_large,
                           estimate=estimate)
        _honour_signal()  # (before anything is put in place)
        paths = sink.finish(result)
    _warn_validity(result.stats, brief=args.quiet)
    if not args.quiet:
        import json

        s = json.loads(paths["summary"].read_text())
        keys = ("hailstones", "impacts", "max_contact_force", "max_impact_force_dynamic_N", "max_indentation_m",
                "max_simultaneous_contacts",
                "steps", "frames", "sim_time_s", "wall_time_s", "real_time_factor", "compile_time_s", "setup_time_s",
                "backend")
        width = max(map(len, keys))
        for k in keys:
            v = s.get(k)
            print(f"{k:<{width}}  {v:.4g}" if isinstance(v, float) else f"{k:<{width}}  {v}")
        print(f"outputs in {out}/" + (f" (animation: {paths['video'].name})" if "video" in paths else ""))
    return 0


def _warn_validity(stats: Any, brief: bool = False) -> None:
    """Warn once when impacts went beyond the model's validity limits (docs/validity.md): with
    the numbers, or (``brief``, under ``-q``) the count alone."""
    from hailstorm.runtime.storm.limits import validity_warning

    msg = validity_warning(stats, brief=brief)
    if msg is not None:
        logging.getLogger("hailstorm").warning("warning: %s", msg)


def _warn_seat_ignored(args: argparse.Namespace, seat: Any, gf: Any) -> None:
    """With --gf the bundle is the seat: say so if the scene file asked for another one."""
    import tomllib

    from hailstorm.precompute.geometry import DEFAULT_COARSENING

    if args.scene is None or not isinstance(tomllib.loads(args.scene.read_text()).get("seat"), dict):
        return
    m = gf.manifest
    opts = m.get("options", {})
    have = {"mesh_size": opts.get("mesh_size"), "order": gf.order, "load": opts.get("load", "point"),
            "volume_size": opts.get("volume_size"), "coarsening": opts.get("coarsening", DEFAULT_COARSENING),
            "young": gf.young, "poisson": gf.poisson}
    differ = [f"{k} = {getattr(seat, k)!r} (bundle: {v!r})" for k, v in have.items() if v != getattr(seat, k)]
    if differ:
        logging.getLogger("hailstorm").warning(
            "warning: the scene's [seat] settings are ignored with --gf (the bundle %s is the seat): %s",
            args.gf, "; ".join(differ))


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``hailstorm`` console script."""
    argv = sys.argv[1:] if argv is None else argv
    parser = _parser()
    leading = []
    while argv and argv[0] in ("-q", "--quiet"):  # `hailstorm -q storm ...`
        leading.append(argv[0])
        argv = argv[1:]
    if argv and not argv[0].startswith("-") and argv[0] not in COMMANDS:
        parser.error(f"unknown command {argv[0]!r} (choose from {', '.join(COMMANDS)}, or give storm options)")
    if not argv or argv[0] not in (*COMMANDS, "-h", "--help"):
        argv = ["storm", *argv]  # plain `hailstorm [storm options]` runs the storm
    args = parser.parse_args(argv[:1] + leading + argv[1:])
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    logging.getLogger("skfem").setLevel(logging.WARNING)
    hook = sys.unraisablehook
    previous = _terminate_as_exception()
    _RECEIVED.clear()
    try:
        if args.command == "precompute":
            rc = _run_precompute(args)
        elif args.command == "info":
            rc = _run_info(args)
        elif args.command == "view":
            rc = _run_view(args)
        else:
            rc = _run_storm(args)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return rc
    except BaseException as exc:
        # a termination signal first: its exception can surface wrapped in another one (a compiled
        # kernel's dispatcher turns an exception raised while it returns into SystemError)
        if _RECEIVED:
            print(f"hailstorm: terminated ({signal.Signals(_RECEIVED[0]).name})", file=sys.stderr)
            return 128 + _RECEIVED[0]
        rc = _user_error(exc, getattr(args, "out", None))
        if rc is None:
            raise
        return rc
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        sys.unraisablehook = hook


def _user_error(exc: BaseException, out: Any) -> int | None:
    """Report an error the user can act on in one line on stderr and return the exit
    code; None for an error that is a defect (its traceback is wanted)."""
    from hailstorm.precompute.geometry import MeshError
    from hailstorm.runtime.bundle.format import BundleError
    from hailstorm.runtime.resources import MissingExtra

    if isinstance(exc, BrokenPipeError):  # `hailstorm info X | head -2`: the reader left; exit quietly
        _silence_stdout()
        return 1
    if isinstance(exc, (MeshError, BundleError, ValueError, MissingExtra)):
        print(f"hailstorm: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    if isinstance(exc, OSError):  # files and directories the user named (missing, read-only, full disk...)
        print(f"hailstorm: error: {_os_error(exc, out)}", file=sys.stderr)
        return EXIT_INPUT
    if isinstance(exc, MemoryError):
        print("hailstorm: error: out of memory (a coarser mesh, a shorter storm or fewer stones needs less)",
              file=sys.stderr)
        return EXIT_INPUT
    if isinstance(exc, KeyboardInterrupt):
        print("hailstorm: interrupted", file=sys.stderr)
        return 130
    return None


#: the signals that end a command cleanly: ``kill`` and a closed terminal
_TERMINATING = (signal.SIGTERM, signal.SIGHUP)
#: the termination signals received (by the handler): whatever exception then ends the
#: command, it ends as that signal (exit 128 + its number)
_RECEIVED: list[int] = []


class _Terminated(Exception):
    """A termination signal, raised in the main thread so that the writers' cleanup runs."""


def _raise_terminated(signum: int, frame: object) -> None:
    _RECEIVED.append(signum)
    raise _Terminated()


def _honour_signal() -> None:
    """Raise :class:`_Terminated` again if a termination signal was received and its exception
    was swallowed on the way (raised inside a callback from C -- numba's compiler, a
    ctypes callback -- Python prints it as "ignored" and goes on): the command still ends
    as that signal, and nothing is put in place."""
    if _RECEIVED:
        raise _Terminated()


def _terminate_as_exception() -> dict[int, Any]:
    """Turn the termination signals into :class:`_Terminated` (only in the main thread);
    returns the previous handlers (empty if none was installed)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    if sys.unraisablehook is not _quiet_swallowed_signal:
        _quiet_swallowed_signal.previous = sys.unraisablehook  # type: ignore[attr-defined]
        sys.unraisablehook = _quiet_swallowed_signal
    return {signum: signal.signal(signum, _raise_terminated) for signum in _TERMINATING}


def _quiet_swallowed_signal(unraisable: Any) -> None:
    """``sys.unraisablehook``: a :class:`_Terminated` raised where Python cannot propagate it (a
    callback from C, a finaliser) is not reported -- :func:`_honour_signal` raises it again where
    it can be -- the rest as before."""
    if isinstance(unraisable.exc_value, _Terminated):
        return
    _quiet_swallowed_signal.previous(unraisable)  # type: ignore[attr-defined]


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _os_error(exc: OSError, out: Any = None) -> str:
    """``[Errno 13] Permission denied: 'x'`` as ``x: Permission denied`` (one line). An error
    that names no file (a write's EFBIG, ENOSPC) names the command's output ``out``."""
    import errno

    if exc.strerror:
        where = ": ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        if not where and out is not None:
            where = f"writing {out}"
        hint = " (a file exceeds the file system's size limit, e.g. FAT32's 4 GiB)" if exc.errno == errno.EFBIG else ""
        return f"{where}: {exc.strerror}{hint}" if where else exc.strerror + hint
    return _one_line(exc)


def _silence_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush does not
    raise BrokenPipeError again (Python's documented recipe)."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # no real file descriptor (captured stdout)
        pass


if __name__ == "__main__":
    sys.exit(main())
