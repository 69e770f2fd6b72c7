"""summary.json names the unit of every figure and separates the one-time compile from the setup;
a storm too large for the memory says the rule it broke."""

import time

import pytest

from hailstorm.runtime.output.files import SUMMARY_UNITS, summary
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.storm.run import run_storm
from hailstorm.runtime.storm.warmup import WarmReport

SCENE = dict(duration=0.02, stones=4, seed=1, spawn_height=0.02, r_min=0.003, r_max=0.006)


def test_every_summary_figure_has_its_unit(gf):
    """Every key of the summary but the sections has an entry in ``units``; the contract's
    ``max_contact_force`` [N] is the one key of the largest contact force (no copy under another
    name), and the largest impact's ``max_impact_force_N`` is never more."""
    d = summary(run_storm(gf, Scene.from_flat(**SCENE), progress=False))
    figures = set(d) - {"scene", "bundle", "units"}
    assert figures <= set(d["units"]) and set(d["units"]) <= set(SUMMARY_UNITS)
    assert d["units"]["max_contact_force"] == d["units"]["max_impact_force_N"] == "N"
    assert "max_contact_force_N" not in d and "max_contact_force_N" not in SUMMARY_UNITS
    assert 0 < d["max_impact_force_N"] <= d["max_contact_force"]
    assert d["units"]["compile_time_s"] == d["units"]["setup_time_s"] == "s"
    assert all(d["units"][k] == "m" for k in figures if k.endswith("_m"))


def test_compile_time_is_apart_from_the_setup(gf, monkeypatch):
    """A warm-up that compiled is ``compile_time_s``, the rest of building the storm
    ``setup_time_s``; one that only loaded the kernels counts as setup (compile 0)."""
    res = run_storm(gf, Scene.from_flat(**SCENE), progress=False)
    assert res.stats["compile_time_s"] == 0.0 and res.stats["setup_time_s"] > 0  # loaded from the cache

    def compiling(self, names=None):
        time.sleep(0.2)
        return WarmReport(compiled=["the narrow-phase kernels"], wall=0.2)

    monkeypatch.setattr(Storm, "warm_up", compiling)
    res = run_storm(gf, Scene.from_flat(**SCENE), progress=False)
    assert res.stats["compile_time_s"] == 0.2
    assert res.stats["setup_time_s"] >= 0.0


def test_the_memory_refusal_states_its_rule(monkeypatch):
    """The refusal names the fraction of the available memory a storm may use and that limit."""
    import hailstorm.runtime.storm.estimate as estimate
    from hailstorm.runtime.storm.scene import StormEstimate, StormTooLarge

    monkeypatch.setattr(estimate, "available_memory", lambda: 10 * 2**30)
    est = StormEstimate(steps=10, stones=1, frames=1, memory_bytes=9 * 2**30)
    with pytest.raises(StormTooLarge, match=r"at most 80% of the memory available \(10 GiB available now, "
                                            r"so at most 8 GiB\)"):
        est.check()
    est.check(allow_large=True)
    StormEstimate(steps=10, stones=1, frames=1, memory_bytes=7 * 2**30).check()
