"""Choices made once: the contact mode and the integrator are read from their objects,
never from string tests scattered through the code (issue 45, "choices made once").

:class:`~hailstorm.runtime.contact.validate.ContactMode` and
:class:`~hailstorm.runtime.storm.hail.Integrator` resolve a name into an object whose
members say what it means (unknowns per contact, the tangential rule; closed form,
backward Euler, explicit). This test greps the library for the string tests they replace.
"""

import re
from pathlib import Path

import pytest

from hailstorm.runtime.contact.validate import ContactMode, check_mode
from hailstorm.runtime.storm.hail import INTEGRATORS, Integrator

ROOT = Path(__file__).resolve().parents[2]
#: the library's folders (the package's top-level modules too)
LIBRARY = [*sorted((ROOT / "runtime").rglob("*.py")), *sorted((ROOT / "precompute").rglob("*.py")),
           ROOT / "cli.py", ROOT / "__init__.py"]
#: a comparison of a mode or an integrator with a name, or a name compared with anything
STRING_TEST = re.compile(r"""(\bmode\s*[!=]=|integrator\s*[!=]=|\.name\s*[!=]=\s*["'](implicit|symplectic|exact)"""
                         r"""|[!=]=\s*["'](sticky|frictionless|implicit|symplectic|exact)["']"""
                         r"""|["'](sticky|frictionless|implicit|symplectic|exact)["']\s*[!=]=|3( \* \w+)? if [\w.]*sticky)""")
#: the compiled kernels take the mode as a plain flag (numba takes no enum): their unknowns per
#: contact are ``3 * s if sticky else s`` on that flag, resolved by the caller's ContactMode
FLAG_TAKERS = {"runtime/compiled/contacts.py", "runtime/compiled/blocks.py"}
#: the shortest sub-step, ``dt / max_substeps``: computed by TimeSettings.min_substep alone
MIN_SUBSTEP = re.compile(r"/\s*[\w.]*max_substeps\b")


def _code_lines(path: Path):
    """(line number, text) of a file's code lines outside docstrings and comments."""
    in_doc = False
    for i, line in enumerate(path.read_text().splitlines(), 1):
        stripped = line.strip()
        quotes = stripped.count('"""') + stripped.count("'''")
        if in_doc:
            in_doc = quotes % 2 == 0
            continue
        if quotes % 2 == 1:
            in_doc = True
            continue
        if quotes or stripped.startswith("#"):
            continue
        yield i, line.split("#", 1)[0]


def test_no_string_tests_of_the_mode_or_the_integrator_outside_their_objects():
    found = [f"{p.relative_to(ROOT)}:{i}: {text.strip()}" for p in LIBRARY for i, text in _code_lines(p)
             if STRING_TEST.search(text) and not (str(p.relative_to(ROOT)) in FLAG_TAKERS
                                                  and re.search(r"3 \* \w+ if sticky else", text))]
    assert not found, "string tests of a choice (use ContactMode / Integrator):\n" + "\n".join(found)


def test_the_grep_finds_what_it_forbids(tmp_path):
    """The pattern is not vacuous: each form of the old string tests matches."""
    for text in ('if mode == "sticky":', 'p = 3 if sticky else 1', 'x = integrator == "implicit"',
                 'if self.name == "symplectic":', 'if "exact" == kind:', 'p = 3 if self.contact.sticky else 1',
                 'm = 3 * s if sticky else s'):
        assert STRING_TEST.search(text), text
    assert not STRING_TEST.search("if mode.sticky:") and not STRING_TEST.search("p = self.contact.contact_mode.dofs")
    for text in ("self.hmin = self.dt / self.max_substeps", "h = dt / time.max_substeps"):
        assert MIN_SUBSTEP.search(text), text


def test_the_minimum_sub_step_is_computed_once():
    """``dt / max_substeps`` is :attr:`TimeSettings.min_substep` (runtime/storm/scene_sections.py), read
    everywhere else, never computed again."""
    found = [f"{p.relative_to(ROOT)}:{i}: {text.strip()}" for p in LIBRARY for i, text in _code_lines(p)
             if MIN_SUBSTEP.search(text) and p != ROOT / "runtime" / "storm" / "scene_sections.py"]
    assert not found, "the minimum sub-step computed again (use TimeSettings.min_substep):\n" + "\n".join(found)


def test_the_objects_say_what_the_choice_means():
    assert check_mode("sticky") is ContactMode.STICKY and ContactMode.STICKY == "sticky"
    assert (ContactMode.STICKY.dofs, ContactMode.FRICTIONLESS.dofs) == (3, 1)
    assert (ContactMode.STICKY.tangential, ContactMode.FRICTIONLESS.tangential) == ("stuck", "free")
    with pytest.raises(ValueError, match="mode must be 'sticky' or 'frictionless'"):
        check_mode("slippery")
    assert tuple(INTEGRATORS) == ("implicit", "symplectic", "exact")
    kinds = [Integrator(n) for n in INTEGRATORS]
    assert [k.backward_euler for k in kinds] == [True, False, False]
    assert [k.explicit for k in kinds] == [False, True, False]
    assert [k.closed_form for k in kinds] == [False, False, True]
    assert [k.omega_dt_factor for k in kinds] == [1.0, 0.5, 1.0]
    assert f"{Integrator.EXACT}" == "exact"
