"""A missing optional extra is one line naming the extra to install (exit 3 on the command line).

The extras' modules are hidden with ``sys.modules[name] = None`` (what Python's import
system reads as "not installed"); the real core-only install is
``tests/contract/test_core_install.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hailstorm.cli import main
from hailstorm.runtime.resources import EXTRAS, MissingExtra, missing_module, require_extra, require_extras

TINY = Path(__file__).resolve().parents[1] / "data" / "tiny-box"


def _hide(monkeypatch, *modules: str) -> None:
    for m in modules:
        monkeypatch.setitem(sys.modules, m, None)


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_precompute_without_gmsh_names_the_precompute_extra(monkeypatch, capsys, tmp_path):
    _hide(monkeypatch, "gmsh")
    assert main(["precompute", "--out", str(tmp_path / "gf")]) == 3
    assert _one_error_line(capsys) == ("hailstorm: error: hailstorm precompute needs the precompute extra "
                                       "(gmsh is not installed): pip install 'hailstorm[precompute]'")
    assert not (tmp_path / "gf").exists()


@pytest.mark.parametrize("module", EXTRAS["precompute"])
def test_each_module_of_the_precompute_extra_is_checked(monkeypatch, capsys, tmp_path, module):
    _hide(monkeypatch, module)
    assert main(["precompute", "-q", "--out", str(tmp_path / "gf")]) == 3
    line = _one_error_line(capsys)
    assert f"({module} is not installed)" in line and "pip install 'hailstorm[precompute]'" in line


def test_the_default_storm_without_the_precompute_extra_says_so_and_names_gf(monkeypatch, capsys, tmp_path):
    _hide(monkeypatch, "skfem")
    assert main(["--out", str(tmp_path / "out"), "--no-video"]) == 3
    line = _one_error_line(capsys)
    assert line.startswith("hailstorm: error: the storm without --gf")
    assert "pip install 'hailstorm[precompute]'" in line and "--gf DIR" in line
    assert not (tmp_path / "out").exists()


def test_workers_without_dask_names_the_dask_extra(monkeypatch, capsys, tmp_path):
    _hide(monkeypatch, "distributed")
    assert main(["precompute", "--workers", "2", "--out", str(tmp_path / "gf")]) == 3
    assert "pip install 'hailstorm[dask]'" in _one_error_line(capsys)


def test_a_storm_without_the_video_extra_skips_the_animation_with_one_note(monkeypatch, capsys, tmp_path):
    _hide(monkeypatch, "matplotlib")
    out = tmp_path / "out"
    assert main(["storm", "--gf", str(TINY), "--duration", "0.01", "--stones", "2", "--out", str(out)]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "hailstorm[video]" in line]
    assert notes == ["note: no animation (matplotlib is not installed): pip install 'hailstorm[video]' for "
                     "storm.mp4, or --no-video"]
    assert (out / "summary.json").is_file() and (out / "impacts.csv").is_file() and (out / "storm.vtkhdf").is_file()
    assert not (out / "storm.mp4").exists() and not (out / "storm.gif").exists()


def test_the_api_refuses_a_video_without_the_extra_before_writing(monkeypatch, tmp_path):
    from hailstorm.runtime import load
    from hailstorm.runtime.output.storm_output import StormOutput

    _hide(monkeypatch, "imageio_ffmpeg")
    with pytest.raises(MissingExtra, match=r"the storm's animation needs the video extra \(imageio_ffmpeg is not "
                                           r"installed\): pip install 'hailstorm\[video\]'"):
        StormOutput(tmp_path / "out", load(TINY), video=True).open()
    assert list(tmp_path.iterdir()) == []


def test_require_extra_imports_or_names_the_extra(monkeypatch):
    assert require_extra("json", "precompute") is sys.modules["json"]
    _hide(monkeypatch, "gmsh")
    with pytest.raises(MissingExtra) as caught:
        require_extra("gmsh", "precompute", "meshing (gmsh)")
    assert str(caught.value) == ("meshing (gmsh) needs the precompute extra (gmsh is not installed): "
                                 "pip install 'hailstorm[precompute]'")
    assert isinstance(caught.value, ImportError) and caught.value.extra == "precompute"
    with pytest.raises(MissingExtra, match=r"^gmsh is not installed; it comes with the precompute extra"):
        require_extra("gmsh", "precompute")


def test_a_submodule_of_a_missing_package_names_the_package(monkeypatch):
    _hide(monkeypatch, "imageio")
    monkeypatch.delitem(sys.modules, "imageio.v2", raising=False)
    with pytest.raises(MissingExtra, match=r"^imageio is not installed; .*'hailstorm\[video\]'$"):
        require_extra("imageio.v2", "video")


def test_an_installed_module_missing_a_dependency_keeps_its_own_error(monkeypatch, tmp_path):
    """Not the extra's fault: the ModuleNotFoundError of the dependency propagates unchanged."""
    (tmp_path / "half_installed_mod.py").write_text("import no_such_dependency_of_it\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ModuleNotFoundError) as caught:
        require_extra("half_installed_mod", "precompute")
    assert not isinstance(caught.value, MissingExtra) and caught.value.name == "no_such_dependency_of_it"


def test_missing_module_and_require_extras_import_nothing(monkeypatch):
    assert missing_module("precompute") is None  # the test extra installs everything
    _hide(monkeypatch, "pyamg")
    assert missing_module("precompute") == "pyamg"
    with pytest.raises(MissingExtra, match=r"^x needs the precompute extra \(pyamg is not installed\).* or y$"):
        require_extras("precompute", "x", hint="or y")


def test_a_storm_without_the_series_extra_writes_the_vtu_series_with_one_note(monkeypatch, capsys, tmp_path):
    """No h5py: the per-frame .vtu series, said in one note; asked for by name, the one-file
    series without h5py is one error line naming the extra, before any work."""
    _hide(monkeypatch, "h5py")
    out = tmp_path / "out"
    args = ["storm", "--gf", str(TINY), "--duration", "0.01", "--stones", "2", "--no-video"]
    assert main([*args, "--out", str(out)]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "hailstorm[series]" in line]
    assert notes == ["note: the ParaView series as .vtu files per frame (h5py is not installed): pip install "
                     "'hailstorm[series]' for one storm.vtkhdf"]
    assert (out / "storm.pvd").is_file() and not (out / "storm.vtkhdf").exists()
    assert main([*args, "--series", "vtkhdf", "--out", str(tmp_path / "other")]) == 3
    line = _one_error_line(capsys)
    assert "needs the series extra (h5py is not installed): pip install 'hailstorm[series]'" in line
    assert not (tmp_path / "other").exists()
