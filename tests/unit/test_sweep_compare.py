"""`phalanx sweep-compare`: two sweeps paired field by field, the runs each reached and
the other did not, the sign test on them (checked against SciPy's binomial test) and each
reach's Wilson interval (checked against SciPy's); hostile results files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import binomtest

from phalanx.analysis.paired import compare, load_sweep, sign_test_p, table, wilson
from phalanx.analysis.sweep import Job, run_job
from phalanx.core.errors import ConfigError


@given(st.integers(0, 60), st.integers(0, 60))
def test_the_sign_test_is_scipys_two_sided_binomial_test(gained: int, lost: int) -> None:
    if gained + lost == 0:
        assert sign_test_p(0, 0) == 1.0
        return
    expected = binomtest(gained, gained + lost, 0.5, alternative="two-sided").pvalue
    assert sign_test_p(gained, lost) == pytest.approx(expected, rel=1e-9, abs=1e-12)


@given(st.integers(1, 500).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))))
def test_the_interval_is_scipys_wilson_interval(counts: tuple[int, int]) -> None:
    k, n = counts
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    low, high = wilson(k, n)
    assert low == pytest.approx(ci.low, abs=1e-9)
    assert high == pytest.approx(ci.high, abs=1e-9)
    assert low <= k / n <= high


@pytest.fixture(scope="module")
def template() -> dict[str, Any]:
    """A row as `phalanx sweep` writes it (a short real run)."""
    job = Job(
        course="field", shape="inline", robots=3, seed=0, controller="ours",
        overrides=(("duration_s", 6.0),),
    )  # fmt: skip
    return json.loads(json.dumps(run_job(job)))


def _rows(template: dict[str, Any], reached: dict[int, bool]) -> list[str]:
    lines = []
    for seed, ok in reached.items():
        row = json.loads(json.dumps(template))
        row["job"]["seed"] = seed
        row["key"] = f"field/inline3/ours/s{seed}/"
        row["goal_reached"] = ok
        row["time_to_goal_s"] = 100.0 + seed if ok else None
        row["route_s"] = 80.0
        lines.append(json.dumps(row))
    return lines


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_runs_are_paired_by_field(template: dict[str, Any], tmp_path: Path) -> None:
    before = {s: s % 3 != 0 for s in range(12)}  # 0, 3, 6, 9 missed
    after = {**before, 0: True, 3: True, 6: True, 4: False, 12: True}  # 12: after only
    pairs = compare(
        load_sweep(_write(tmp_path / "a.jsonl", _rows(template, before))),
        load_sweep(_write(tmp_path / "b.jsonl", _rows(template, after))),
    )
    assert len(pairs) == 1
    p = pairs[0]
    assert p.group == ("field", "inline", 3, "ours")
    assert p.runs == 12
    assert p.reached == (8, 10)
    assert p.gained == (0, 3, 6)
    assert p.lost == (4,)
    assert p.p_value == pytest.approx(binomtest(3, 4, 0.5).pvalue)
    # (seeds both reached: 1, 2, 5, 7, 8, 10, 11; their median time 107 s)
    assert p.time_ratio == (pytest.approx(107.0 / 80.0), pytest.approx(107.0 / 80.0))
    row = table(pairs)[2]
    assert "| 3 (0, 3, 6) | 1 (4) |" in row
    assert "| 8 (" in row


def test_lines_that_are_not_runs_are_skipped_and_counted(
    template: dict[str, Any], tmp_path: Path
) -> None:
    lines = _rows(template, {0: True, 1: False})
    bad = json.loads(lines[0])
    bad["job"]["seed"] = 2
    bad["goal_reached"] = "yes"  # not a boolean
    worse = json.loads(lines[0])
    worse["job"]["seed"] = 3
    worse["deadlock_reverses"] = -1
    odd = json.loads(lines[0])
    odd["job"]["seed"] = 4
    odd["episode_share"] = 7.0  # a share above 1
    lines += [json.dumps(bad), json.dumps(worse), json.dumps(odd), "[1, 2]", '{"key": "torn', ""]
    for seed, (where, field, value) in enumerate(
        [
            ("job", "robots", 5.0),  # a count that is not a whole number
            ("job", "robots", True),
            ("job", "shape", ["inline"]),
            ("row", "episode_share", 10**400),  # too large for a float
            ("row", "deadlock_reverses", float("inf")),
        ],
        start=5,
    ):
        row = json.loads(lines[0])
        row["job"]["seed"] = seed
        (row["job"] if where == "job" else row)[field] = value
        lines.append(json.dumps(row))
    sweep = load_sweep(_write(tmp_path / "a.jsonl", lines))
    assert sorted(seed for _, seed in sweep.runs) == [0, 1]
    assert sweep.skipped == 11


def test_one_field_twice_in_a_file_is_an_error(template: dict[str, Any], tmp_path: Path) -> None:
    lines = _rows(template, {0: True}) * 2
    with pytest.raises(ConfigError, match="a second run of field/inline3/ours seed 0"):
        load_sweep(_write(tmp_path / "a.jsonl", lines))


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    command = [str(Path(sys.executable).parent / "phalanx"), "sweep-compare", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=60, check=False)


def test_the_command_prints_the_table_and_refuses_what_it_cannot_compare(
    template: dict[str, Any], tmp_path: Path
) -> None:
    a = _write(tmp_path / "a.jsonl", [*_rows(template, {0: False, 1: True}), "not json"])
    b = _write(tmp_path / "b.jsonl", _rows(template, {0: True, 1: True}))
    done = _cli(str(a), str(b), "--markdown")
    assert done.returncode == 0, done.stderr
    assert "| field | inline | 3 | ours | 2 | 1 (" in done.stdout
    assert "1 (0)" in done.stdout
    plain = _cli(str(a), str(b))  # a pipe: plain text in 80 columns
    assert plain.returncode == 0, plain.stderr
    assert "|" not in plain.stdout
    assert "nan" not in plain.stdout
    assert max(len(line) for line in plain.stdout.splitlines()) <= 80
    assert "gained (seeds):" in plain.stdout
    assert "1 lines that are not sweep runs, skipped" in done.stderr
    twice = _write(tmp_path / "twice.jsonl", _rows(template, {0: True}) * 2)
    refused = _cli(str(a), str(twice))
    assert refused.returncode == 2
    assert "a second run of" in refused.stderr
    other = json.loads(_rows(template, {0: True})[0])
    other["job"]["shape"] = "wedge"
    apart = _write(tmp_path / "wedge.jsonl", [json.dumps(other)])
    assert _cli(str(a), str(apart)).returncode == 2
    assert _cli(str(a), str(tmp_path / "missing.jsonl")).returncode == 2
