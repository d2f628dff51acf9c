"""Compiled kernels: numba's, where it is installed (the `fast` extra), for navigation's
loops that numpy runs as tens of calls on small arrays (the free way along the candidate
headings, the map's update, the route's wavefront, which echoes are the fleet's robots).

A kernel does the arithmetic of the numpy code it stands in for, operation for operation
(no fused multiply-add, no reordered sums: numba compiles without fast-math), so the two
give the same floats to the bit; the tests compare them. Without numba, or with
`PHALANX_KERNELS=numpy` in the environment, the numpy code runs. The kernels cost a
process about half a second (numba's import, their code loaded from numba's on-disk
cache; compiled there first in a fresh environment, about 3 s) and some 120 MB:
they pay where one process steps a navigating fleet for long (`phalanx run`, a sweep's
workers), not in a robot's agent process (`numpy_unless_asked`).
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType

from phalanx.core.errors import ConfigError

ENV = "PHALANX_KERNELS"
CHOICES = ("numba", "numpy")

_log = logging.getLogger(__name__)


def numpy_unless_asked() -> None:
    """Run numpy's code in this process unless `PHALANX_KERNELS` asks for numba: a robot's
    agent process, whose 20 Hz steps take a fraction of a millisecond either way, needs
    neither numba's start-up nor its memory (about 120 MB).
    """
    os.environ.setdefault(ENV, "numpy")
    kernels.cache_clear()


def choice() -> str:
    """Which kernels the environment asks for: `numba` (the default) or `numpy`;
    ConfigError for anything else (the batch runner and an agent process ask before
    they start, so a misspelt choice never stops a run half-way).
    """
    wanted = os.environ.get(ENV, "numba").strip().lower() or "numba"
    if wanted not in CHOICES:
        raise ConfigError(f"{ENV}={wanted!r}: expected one of {', '.join(CHOICES)}")
    return wanted


@functools.cache
def kernels(module: str) -> ModuleType | None:
    """The kernels module `module` (which imports numba), or None: numba not installed,
    not working here (its import or the kernels' set-up failed: logged once), or turned
    off (`PHALANX_KERNELS=numpy`).
    """
    if choice() == "numpy" or importlib.util.find_spec("numba") is None:
        return None
    try:
        return importlib.import_module(module)
    except Exception as exc:  # (numba not built for this numpy; no cache it may write to)
        _log.warning("compiled kernels off, numpy's code runs instead: %s", exc)
        return None


@contextmanager
def chosen(kind: str) -> Iterator[None]:
    """Run the block with `kind`'s kernels (`numba` or `numpy`), as `PHALANX_KERNELS`
    would choose them: for tests and benchmarks that compare the two in one process.
    """
    before = os.environ.get(ENV)
    os.environ[ENV] = kind
    kernels.cache_clear()
    try:
        choice()
        yield
    finally:
        if before is None:
            del os.environ[ENV]
        else:
            os.environ[ENV] = before
        kernels.cache_clear()
