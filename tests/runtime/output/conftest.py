"""Fixtures of the output tests: storm output folders for the viewer (``hailstorm view``)."""

import pytest


def _storm_out(out, gf_path, series: str, duration: float = 0.1):
    from hailstorm.runtime.bundle.read import load
    from hailstorm.runtime.output.storm_output import StormOutput
    from hailstorm.runtime.storm.run import run_storm
    from hailstorm.runtime.storm.scene import Scene

    gf = load(gf_path)
    data = Scene.default().to_dict()
    data["storm"]["duration"] = duration
    scene = Scene.from_dict(data, source="test")
    with StormOutput(out, gf, video=False, series=series, progress=False) as sink:
        result = run_storm(gf, scene, progress=False, on_frame=sink.add)
        sink.finish(result)
    return out


@pytest.fixture(scope="session")
def viewer_storm(tmp_path_factory, seat_bundle):
    """A 0.1 s default storm on the coarse saddle (``seat_bundle``): its output folder with
    ``storm.vtkhdf`` (26 frames, about 50 impacts); the viewer's tests write their pages elsewhere."""
    return _storm_out(tmp_path_factory.mktemp("viewer") / "out", seat_bundle, "vtkhdf")


@pytest.fixture(scope="session")
def viewer_storm_vtu(tmp_path_factory, seat_bundle):
    """The same storm as :func:`viewer_storm`, its series as ``.vtu`` files per frame."""
    return _storm_out(tmp_path_factory.mktemp("viewer") / "out-vtu", seat_bundle, "vtu")
