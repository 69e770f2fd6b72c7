"""The machine's resources that both stages check before they start work: memory, and
the optional extras (``pip install "hailstorm[EXTRA]"``) installed beside the core.

The core (numpy, scipy, numba, llvmlite, threadpoolctl, tqdm) loads a bundle and
runs contacts and storms; each stage beyond it comes with an extra of
``pyproject.toml`` (:data:`EXTRAS`). Code that needs one imports its modules through
:func:`require_extra`, so that a missing extra is one line naming what to install
(:class:`MissingExtra`; the command line prints it and exits 3).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
from types import ModuleType

__all__ = ["EXTRAS", "MissingExtra", "available_memory", "missing_module", "require_extra", "require_extras"]

#: the optional extras of ``pyproject.toml`` -> the modules (import names) each installs
EXTRAS: dict[str, tuple[str, ...]] = {
    "precompute": ("gmsh", "skfem", "meshio", "pyamg", "cholespy"),
    "video": ("matplotlib", "imageio", "imageio_ffmpeg"),
    "dask": ("distributed",),
    "series": ("h5py",),
}


class MissingExtra(ImportError):
    """A module of an optional extra is not installed.

    The message is one line naming the extra and the command that installs it.

    Parameters
    ----------
    module : str
        The import name that is missing (``"gmsh"``).
    extra : str
        The extra that installs it (``"precompute"``).
    purpose : str, optional
        What needs it (``"hailstorm precompute"``); the message opens with it.
    hint : str, optional
        An alternative to installing, appended to the message.
    """

    def __init__(self, module: str, extra: str, purpose: str | None = None, hint: str | None = None) -> None:
        self.module, self.extra, self.purpose = module, extra, purpose
        if purpose:
            msg = f"{purpose} needs the {extra} extra ({module} is not installed): pip install 'hailstorm[{extra}]'"
        else:
            msg = f"{module} is not installed; it comes with the {extra} extra: pip install 'hailstorm[{extra}]'"
        if hint:
            msg += f" {hint}"
        super().__init__(msg, name=module)


def _absent(module: str) -> bool:
    """True if ``module`` cannot be found (without importing it; None in ``sys.modules`` counts as absent)."""
    try:
        return importlib.util.find_spec(module) is None
    except (ImportError, ValueError):  # a missing parent package, or a module without a spec
        return True


def require_extra(module: str, extra: str, purpose: str | None = None) -> ModuleType:
    """Import ``module`` of the optional ``extra``, or raise :class:`MissingExtra`.

    Parameters
    ----------
    module : str
        Import name (``"gmsh"``, ``"imageio.v2"``).
    extra : str
        The extra of :data:`EXTRAS` that installs it.
    purpose : str, optional
        What needs it, for the message.

    Returns
    -------
    module
        The imported module.

    Raises
    ------
    MissingExtra
        The module (or its top-level package) is not installed. Any other import
        failure (an installed module that fails to load) propagates unchanged.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.split(".")[0]
        if exc.name is not None and exc.name.split(".")[0] != top:
            raise  # a dependency of the module is missing: not the extra's fault, keep the traceback
        raise MissingExtra(top, extra, purpose) from None


def missing_module(extra: str) -> str | None:
    """The first module of ``extra`` that is not installed, or None if all are (nothing is imported).

    Parameters
    ----------
    extra : str
        A key of :data:`EXTRAS`.
    """
    return next((m for m in EXTRAS[extra] if _absent(m)), None)


def require_extras(extra: str, purpose: str, hint: str | None = None) -> None:
    """Check up front that every module of ``extra`` is installed (nothing is imported).

    Parameters
    ----------
    extra : str
        A key of :data:`EXTRAS`.
    purpose : str
        What needs it, for the message (``"hailstorm precompute"``).
    hint : str, optional
        An alternative to installing, appended to the message.

    Raises
    ------
    MissingExtra
        Naming the first module found missing.
    """
    missing = missing_module(extra)
    if missing is not None:
        raise MissingExtra(missing, extra, purpose, hint)


def available_memory() -> int | None:
    """Memory available to a new allocation [bytes] (``MemAvailable`` of
    ``/proc/meminfo``, else the physical memory), or None if unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None
