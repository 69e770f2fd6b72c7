"""The scene as sections: one typed record per TOML section, ``[seat]`` apart."""

from __future__ import annotations

import dataclasses
import tomllib
from importlib import resources

import pytest

from hailstorm.runtime.storm.scene import Scene, SceneError, SeatSettings
from hailstorm.runtime.storm.scene_sections import (
    ContactSettings,
    HailSettings,
    OutputSettings,
    StormSettings,
    TimeSettings,
    ValiditySettings,
)

SECTIONS = {"storm": StormSettings, "hail": HailSettings, "contact": ContactSettings, "time": TimeSettings,
            "output": OutputSettings, "validity": ValiditySettings}


def _packaged() -> dict:
    return tomllib.loads(resources.files("hailstorm.meshes").joinpath("default_scene.toml").read_text())


def test_default_scene_is_the_packaged_file_section_by_section():
    """Scene.default() holds every key of the packaged TOML in its section's record, and the
    records' own defaults are the same values (Scene() == Scene.default())."""
    toml = _packaged()
    sc = Scene.default()
    assert set(toml) == {*SECTIONS, "seat"}
    for sec, rec in SECTIONS.items():
        record = getattr(sc, sec)
        assert type(record) is rec
        assert {f.name for f in dataclasses.fields(rec)} >= set(toml[sec])
        for k, v in toml[sec].items():
            assert getattr(record, k) == (tuple(v) if isinstance(v, list) else v), (sec, k)
    assert sc.storm.stones is None  # commented out in the file
    assert Scene() == sc
    assert SeatSettings.default() == SeatSettings(**toml["seat"]) == SeatSettings()


def test_seat_is_not_a_scene_field(tmp_path):
    sc = Scene.default()
    assert not hasattr(sc, "mesh_size") and "seat" not in sc.to_dict()
    assert not any(hasattr(getattr(sc, sec), "mesh_size") for sec in SECTIONS)
    p = tmp_path / "s.toml"
    p.write_text("[seat]\nmesh_size = 0.004\n[storm]\nduration = 0.1\n")
    assert Scene.from_toml(p) == sc.with_(duration=0.1)
    assert SeatSettings.from_toml(p) == SeatSettings(mesh_size=0.004)  # the rest: the packaged defaults
    p.write_text("[seat]\norder = 3\n")
    with pytest.raises(SceneError, match="order must be 1 or 2"):
        Scene.from_toml(p)  # a bad [seat] is still refused when the scene is read
    with pytest.raises(SceneError, match="order must be 1 or 2"):
        SeatSettings.from_toml(p)
    with pytest.raises(SceneError, match=r"unknown scene setting 'mesh_size' \(a \[seat\] setting"):
        Scene.from_flat(mesh_size=0.004)


def test_scene_round_trips_through_toml_with_its_seat(tmp_path):
    """Every section changed away from its default survives to_toml -> from_toml."""
    sc = Scene(
        storm=StormSettings(duration=0.3, rate=50.0, stones=7, seed=4, spawn_height=0.03, margin=0.0,
                            wind=(1.5, -0.5, 0.0)),
        hail=HailSettings(distribution="uniform", r_min=0.003, r_max=0.006, scale=0.001, density=900.0,
                          drag=False, cd=0.5, rho_air=1.1),
        contact=ContactSettings(mode="sticky", unilateral=False, restitution=0.3, patch="none",
                                patch_min_radius=5e-4, patch_tolerance=0.1),
        time=TimeSettings(dt=1e-4, integrator="exact", adaptive=False, omega_dt=0.1, approach_fraction=0.2,
                          max_substeps=8, rest_speed=0.02),
        output=OutputSettings(fps=100.0),
        validity=ValiditySettings(pad_density=200.0),
    )
    for sec in SECTIONS:  # really every section differs from the default
        assert getattr(sc, sec) != getattr(Scene.default(), sec)
    seat = SeatSettings(mesh_size=0.004, order=2, young=3e6, poisson=0.3)
    p = tmp_path / "scene.toml"
    text = sc.to_toml(p, seat=seat)
    assert tomllib.loads(text) == {**sc.to_dict(), "seat": seat.to_dict()}
    assert Scene.from_toml(p) == sc
    assert SeatSettings.from_toml(p) == seat
    assert "[seat]" not in sc.to_toml()


def test_flat_keys_route_to_their_sections():
    sc = Scene.from_flat(duration=0.1, stones=12, r_min=0.003, mode="sticky", dt=5e-4, fps=100.0)
    assert sc.storm == StormSettings(duration=0.1, stones=12)
    assert sc.hail == HailSettings(r_min=0.003)
    assert sc.contact == ContactSettings(mode="sticky")
    assert sc.time == TimeSettings(dt=5e-4)
    assert sc.output == OutputSettings(fps=100.0)
    ch = sc.with_(integrator="implicit", seed=3)
    assert (ch.time.integrator, ch.time.dt, ch.storm.seed, ch.storm.stones) == ("implicit", 5e-4, 3, 12)
    assert (ch.hail, ch.contact, ch.output) == (sc.hail, sc.contact, sc.output)  # untouched sections shared
    assert sc.time.integrator == "exact"  # with_ copies
    with pytest.raises(SceneError, match="unknown scene setting 'durration'"):
        sc.with_(durration=1.0)
    with pytest.raises(SceneError, match="dt .* must not exceed duration"):
        sc.with_(dt=0.5)  # the one check across sections


def test_sections_are_frozen_and_validate_on_their_own():
    sc = Scene.default()
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.time.dt = 1e-3  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.storm = StormSettings()  # type: ignore[misc]
    for make, match in [
        (lambda: StormSettings(duration=-1.0), "duration must be a positive"),
        (lambda: StormSettings(wind=(1.0, 2.0)), "wind must be three"),
        (lambda: HailSettings(r_min=0.01, r_max=0.005), "r_max"),
        (lambda: HailSettings(r_max=float("inf")), "r_max must be a finite radius"),
        (lambda: HailSettings(drag="yes"), "drag must be true or false"),
        (lambda: ContactSettings(restitution=1.5), "restitution"),
        (lambda: TimeSettings(integrator="rk4"), "integrator"),
        (lambda: TimeSettings(max_substeps=0), "max_substeps"),
        (lambda: OutputSettings(fps=0.0), "fps must be a positive"),
        (lambda: SeatSettings(poisson=0.5), "poisson"),
        (lambda: Scene(time=HailSettings()), "time must be a TimeSettings"),
    ]:
        with pytest.raises(SceneError, match=match):
            make()
    assert StormSettings(wind=[1, 0, 0]).wind == (1.0, 0.0, 0.0)


def test_number_fields_hold_floats():
    """A section is the one typed source its storm part reads (no copies cast at each part):
    an integer given for a number field is stored as a float, so the compiled kernels see
    one type whichever way the scene was written."""
    import numpy as np

    t = TimeSettings(rest_speed=0, dt=np.float32(1e-4))
    assert type(t.rest_speed) is float and t.rest_speed == 0.0
    assert type(t.dt) is float
    c = ContactSettings(restitution=1, patch_tolerance=np.int64(1))
    assert type(c.restitution) is float and type(c.patch_tolerance) is float
    assert type(TimeSettings(max_substeps=np.int64(7)).max_substeps) is int  # integers stay integers


@pytest.mark.parametrize("value", [0.0, -70.0, float("nan"), "70"])
def test_pad_density_must_be_a_positive_number(tmp_path, value):
    """[validity] pad_density (the contact-time limit's foam density) is refused unless a positive number."""
    with pytest.raises(SceneError, match="pad_density must be"):
        Scene.from_flat(pad_density=value)
    assert Scene.from_flat(pad_density=200).validity.pad_density == 200.0
