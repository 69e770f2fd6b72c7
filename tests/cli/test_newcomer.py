"""What a newcomer stumbled on at the command line (issue: a lean house), each held here."""

import pytest

from hailstorm import cli
from hailstorm.runtime.storm.limits import validity_warning
from hailstorm.runtime.storm.scene import Scene


def _help(capsys, *argv):
    with pytest.raises(SystemExit) as exc:
        cli.main(list(argv))
    assert exc.value.code == 0
    return capsys.readouterr().out


def test_the_top_level_help_names_the_storm_options_a_bare_run_takes(capsys):
    text = " ".join(_help(capsys, "--help").split())
    assert "-q" in text and "--no-video" in text and "hailstorm storm --help" in text


def test_info_says_what_its_argument_is(capsys):
    text = " ".join(_help(capsys, "info", "--help").split())
    assert "bundle a bundle directory" in text


def test_quiet_warns_in_one_short_line():
    """``-q``: the count and where the numbers are; without it, the numbers."""
    stats = {"impacts": 99, "impacts_beyond_any_limit": 99, "max_indentation_thickness_ratio": 0.29,
             "limit_indentation_thickness_ratio": 0.1, "impacts_beyond_indentation_limit": 38,
             "max_contact_radius_ratio": 0.7, "limit_contact_radius_ratio": 0.8, "impacts_beyond_radius_limit": 0,
             "max_strain_ratio": 0.29, "limit_strain_ratio": 0.05, "impacts_beyond_strain_limit": 99}
    brief = validity_warning(stats, brief=True)
    assert brief.startswith("99 of 99 impacts") and "summary.json" in brief and "0.29" not in brief
    assert len(brief) < 140 and "0.29" in validity_warning(stats)
    assert validity_warning({**stats, "impacts_beyond_any_limit": 0}, brief=True) is None


def test_a_rate_announces_its_mean_count_and_a_count_its_own():
    """A rate draws a Poisson number of stones (the default storm: 206 for a mean of 200): the
    announcement says ``~200``; ``stones = N`` is exact."""
    assert "~200 stones" in Scene.default().estimate().describe()
    assert " 12 stones" in Scene.from_flat(stones=12, duration=0.1).estimate().describe()
