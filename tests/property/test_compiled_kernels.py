"""The compiled kernels (numba; `phalanx.core.compiled`) give numpy's floats to the bit
where they differ most easily: the fleet map's arcs' test on a disc's edge, where the
squared distances leave the answer in doubt and both take `hypot`. (The clearance pass,
the map update and the wavefront are held to their plain references on both paths in
`tests/unit/test_grid_speed_clearance.py` and `tests/unit/test_grid_speed.py`.) An agent
process keeps to numpy unless asked; an unknown choice stops a run before it starts;
kernels that cannot be set up leave numpy running; the warm-up readies every kernel a
navigating run calls.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.navigation.clearance import KERNELS
from phalanx.agents.perception import SonarGeometry
from phalanx.core.compiled import ENV, chosen, kernels
from phalanx.core.config_files import load_robot
from phalanx.core.errors import ConfigError

SONAR = SonarGeometry.from_params(load_robot("p3dx"))
REPO = Path(__file__).resolve().parents[2]


def _on_edges(seed: int, radius_m: float) -> tuple[Any, tuple[Any, ...]]:
    """Four readings and twelve discs (owned by readings in order, some by none): half
    of each owner's transducers at the range that puts their echo's point nearest its
    disc on the disc's edge, to a few units in the last place; the rest anywhere.
    """
    rng = np.random.default_rng(seed)
    units, readings, discs = SONAR.unit_x_m.size, 4, 12
    owner = np.sort(rng.integers(0, readings, discs))
    cx, cy = rng.uniform(-3.0, 3.0, (2, discs, 1))
    dirs = SONAR.nearest_dirs(cx, cy)
    apart = np.hypot(cx - SONAR.unit_x_m, cy - SONAR.unit_y_m)
    edge = np.maximum(apart - radius_m, 0.0) * (1.0 + rng.integers(-3, 4, apart.shape) * 1e-16)
    r = rng.uniform(0.0, 5.0, (readings, units))
    for k in range(discs):
        on_edge = rng.random(units) < 0.5
        r[owner[k], on_edge] = edge[k, on_edge]
    return r, (owner, (cx, cy), radius_m, dirs)


def _arcs_met(kind: str, r: Any, discs: tuple[Any, ...]) -> Any:
    met = np.zeros(r.shape, dtype=bool)
    with chosen(kind):
        SONAR.arcs_met(r, *discs, met)
    return met


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.05, 0.5))
def test_echoes_on_a_discs_edge_meet_it_in_the_compiled_test_as_in_numpys(
    seed: int, radius_m: float
) -> None:
    r, discs = _on_edges(seed, radius_m)
    assert np.array_equal(_arcs_met("numpy", r, discs), _arcs_met("numba", r, discs))


def test_the_edges_drawn_are_where_the_squared_distances_leave_the_answer_in_doubt() -> None:
    """(So the test above takes both paths' `hypot`, and finds echoes that meet.)"""
    doubtful = met = 0
    for seed in range(40):
        r, (owner, (cx, cy), radius_m, dirs) = _on_edges(seed, 0.2)
        dx = SONAR.unit_x_m + r[owner] * dirs[0] - cx
        dy = SONAR.unit_y_m + r[owner] * dirs[1] - cy
        d2, r2 = dx * dx + dy * dy, radius_m * radius_m
        doubtful += int(np.count_nonzero(abs(d2 - r2) <= r2 * 1e-9))
        met += int(np.count_nonzero(_arcs_met("numba", r, (owner, (cx, cy), radius_m, dirs))))
    assert doubtful > 0
    assert met > 0


def test_numba_runs_where_installed_and_not_when_turned_off_or_unknown() -> None:
    """The dev extra installs numba, so the tests compare its loops, not numpy's twice."""
    with chosen("numba"):
        assert kernels(KERNELS) is not None
    with chosen("numpy"):
        assert kernels(KERNELS) is None
    with pytest.raises(ConfigError, match="PHALANX_KERNELS='fortran'"), chosen("fortran"):
        pass
    assert kernels.cache_info().currsize == 0  # (each choice forgotten as it ends)


@pytest.mark.parametrize(("asked", "runs"), [(None, "numpy"), ("numba", "numba")])
def test_an_agent_process_keeps_to_numpy_unless_asked(asked: str | None, runs: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != ENV}
    if asked is not None:
        env[ENV] = asked
    probe = (
        "from phalanx.core.compiled import kernels, numpy_unless_asked\n"
        "from phalanx.agents.navigation.clearance import KERNELS\n"
        "numpy_unless_asked()\n"
        "print('numpy' if kernels(KERNELS) is None else 'numba')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=60,
        check=True,
    )  # fmt: skip
    assert done.stdout.strip() == runs


def test_kernels_that_cannot_be_set_up_leave_numpys_code_running(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """(numba built for another numpy, no cache it may write to: the module does not load.)"""
    with chosen("numba"), caplog.at_level(logging.WARNING, logger="phalanx.core.compiled"):
        assert kernels("phalanx.agents.no_such_kernels") is None
    assert "numpy's code runs instead" in caplog.text


def test_a_choice_it_does_not_know_stops_a_run_before_it_starts() -> None:
    """(Not at the first obstacle, where navigation would first ask for its kernels.)"""
    env = {**os.environ, ENV: "fortran"}
    scenario = str(REPO / "configs" / "scenarios" / "nav_field_wedge3.toml")
    done = subprocess.run(
        [sys.executable, "-m", "phalanx", "run", scenario, "--no-figures", "--no-recording"],
        env=env, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode != 0
    assert "PHALANX_KERNELS='fortran': expected one of numba, numpy" in done.stderr
    assert "Traceback" not in done.stderr


def test_warming_the_kernels_readies_every_one_a_navigating_run_calls() -> None:
    """In a fresh process: after `warm_kernels` each of the four has its code, and half a
    minute of a navigating wedge in a field (a leader steering, mapping and planning,
    followers' echoes of one another) makes numba load or compile nothing more."""
    probe = (
        "import json\n"
        "from phalanx.agents.navigation import clearance_kernels, grid_kernels, warm_kernels\n"
        "from phalanx.agents import perception_kernels\n"
        "from phalanx.agents.perception import SonarGeometry\n"
        "from phalanx.analysis.sweep import Job\n"
        "from phalanx.core.config_files import load_robot\n"
        "from phalanx.runtime.batch import BatchRunner\n"
        "fns = [clearance_kernels.corridor, grid_kernels.add_readings, grid_kernels.wavefront,\n"
        "       perception_kernels.arcs_met]\n"
        "warm_kernels(SonarGeometry.from_params(load_robot('p3dx')))\n"
        "warm = [len(f.signatures) for f in fns]\n"
        "runner = BatchRunner(Job('field', 'wedge', 3, 4).scenario())\n"
        "runner.run(until=lambda b: b.done >= 300)\n"
        "print(json.dumps([warm, [len(f.signatures) for f in fns]]))\n"
    )
    env = {**os.environ, ENV: "numba"}
    done = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=90,
        check=True,
    )  # fmt: skip
    warm, after = json.loads(done.stdout.strip().splitlines()[-1])
    assert all(warm), warm  # (each kernel has its code after the warm-up)
    assert after == warm  # (and the run needed no other)
