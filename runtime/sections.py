"""Settings records laid out as the sections of a TOML file (the scene file's).

A record is a frozen dataclass deriving from :class:`Section`: its fields are the
keys of its ``[section]``, its ``__post_init__`` checks them with
:func:`check_types`, :func:`check_positive` and :func:`check_bool` (a bad value
raises :class:`SceneError` naming the key), and
:meth:`Section.from_dict` / :meth:`Section.to_dict` map it to and from the TOML
section. The storm's records (:mod:`hailstorm.runtime.storm.scene_sections`) and the default
seat's (:mod:`hailstorm.runtime.seat_settings`) are built on it; neither imports the other's.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, ClassVar, Mapping

import numpy as np

__all__ = ["TYPES", "SceneError", "Section", "check_bool", "check_positive", "check_types", "packaged_toml", "read_toml"]


class SceneError(ValueError):
    """A scene file or value is invalid (a settings record's key named in the message).

    Defined here, with the records it checks, so that the settings (this module, the storm's
    scene and the default seat's :mod:`hailstorm.runtime.seat_settings`) import nothing of the
    storm; :mod:`hailstorm.runtime.storm.errors` re-exports it beside :class:`StormTooLarge`."""


#: Python types a scene value may have, per field annotation (``Mode`` and ``Integrator``:
#: the storm's choices, strings)
TYPES: dict[str, tuple[type, ...]] = {
    "float": (int, float), "int": (int,), "bool": (bool,), "str": (str,), "Mode": (str,), "Integrator": (str,),
    "int | None": (int, type(None)), "float | None": (int, float, type(None)),
}


def check_types(record: Any) -> None:
    """Raise :class:`SceneError` for a field whose value has the wrong Python type."""
    for f in dataclasses.fields(record):
        types = TYPES.get(str(f.type))
        v = getattr(record, f.name)
        if types is not None and isinstance(v, np.integer) and int in types:  # numpy integers are integers
            v = int(v)
            object.__setattr__(record, f.name, v)
        if str(f.type) in ("float", "float | None") and isinstance(v, (int, np.floating)) and not isinstance(v, bool):
            v = float(v)  # a number field holds a float: the parts pass it to the kernels as it is
            object.__setattr__(record, f.name, v)
        if types is not None and (not isinstance(v, types) or (isinstance(v, bool) and bool not in types)):
            kind = {"float": "a number", "int": "an integer", "bool": "true or false",
                    "int | None": "an integer", "float | None": "a number"}.get(str(f.type), "a string")
            raise SceneError(f"{f.name} must be {kind}, got {v!r}")


def check_positive(record: Any, names: tuple[str, ...], allow_zero: bool = False) -> None:
    """Raise :class:`SceneError` unless every named field is a finite positive
    (or, with ``allow_zero``, non-negative) number."""
    for name in names:
        v = getattr(record, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (v < 0 or (v == 0 and not allow_zero)):
            raise SceneError(f"{name} must be a {'non-negative' if allow_zero else 'positive'} number, got {v!r}")


def check_bool(record: Any, names: tuple[str, ...]) -> None:
    """Raise :class:`SceneError` unless every named field is true or false."""
    for name in names:
        if not isinstance(getattr(record, name), bool):
            raise SceneError(f"{name} must be true or false, got {getattr(record, name)!r}")


class Section:
    """TOML layout of a settings record (one ``[section]`` of the scene file)."""

    #: the record's TOML section
    SECTION: ClassVar[str] = ""

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        """The record's keys (its fields), in TOML order."""
        return tuple(f.name for f in dataclasses.fields(cls))  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, Any]:
        """``{key: value}`` as in the TOML section (None values omitted, tuples as lists)."""
        out = {}
        for k in self.keys():
            v = getattr(self, k)
            if v is not None:
                out[k] = list(v) if isinstance(v, tuple) else v
        return out

    @classmethod
    def from_dict(cls, body: Any, *, source: str = "scene") -> Any:
        """Build from the TOML section's ``{key: value}`` (integers accepted for numbers).

        Raises
        ------
        SceneError
            On an unknown key or a bad value (the message names ``source``).
        """
        if not isinstance(body, Mapping):
            raise SceneError(f"{source}: [{cls.SECTION}] must be a table")
        kinds = {f.name: str(f.type) for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        kwargs: dict[str, Any] = {}
        for k, v in body.items():
            if k not in kinds:
                raise SceneError(f"{source}: unknown key {k!r} in [{cls.SECTION}]; known keys: {', '.join(kinds)}")
            # users write 1 for 1.0
            kwargs[k] = float(v) if kinds[k] == "float" and isinstance(v, int) and not isinstance(v, bool) else v
        try:
            return cls(**kwargs)
        except (SceneError, TypeError) as exc:
            raise SceneError(f"{source}: {exc}") from None


def read_toml(path: Path) -> dict[str, Any]:
    """The TOML file at ``path`` as a dict; :class:`SceneError` (one line) if it cannot be read
    or is not UTF-8 TOML."""
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise SceneError(f"{path} is not a UTF-8 text file (a TOML scene): byte {exc.start} is "
                         f"{exc.object[exc.start:exc.start + 1]!r}") from None
    except OSError as exc:
        raise SceneError(f"cannot read scene file {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path} is not valid TOML: {exc}") from None


def packaged_toml() -> dict[str, Any]:
    """The packaged default scene file (``hailstorm.meshes/default_scene.toml``) as a dict."""
    return tomllib.loads(resources.files("hailstorm.meshes").joinpath("default_scene.toml").read_text())
