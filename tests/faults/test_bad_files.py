"""A careless user: malformed scenario and deployment files and values. Each ends the
command with exit code 2 and one message naming the file, the field (or the line) and
the fix, no traceback; `--debug` shows the traceback. Resources are bounded: a
10 000-robot file is refused before it costs anything.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from fleetlab import CLI, WEDGE

from phalanx.core.config_files import CONFIG_ROOT

WEDGE_TEXT = WEDGE.read_text()


def _cycle() -> str:
    text = WEDGE_TEXT.replace('robot = "r2"\nfollows = "r1"', 'robot = "r2"\nfollows = "r3"')
    return text.replace('robot = "r3"\nfollows = "r1"', 'robot = "r3"\nfollows = "r2"')


def _many(n: int) -> str:
    text = re.sub(r"\[\[formation\.slots\]\].*", "", WEDGE_TEXT, flags=re.S)
    text += '[[formation.slots]]\nrobot = "r0"\nx_m = 0.0\ny_m = 0.0\n'
    for i in range(1, n):
        text += (
            f'[[formation.slots]]\nrobot = "r{i}"\nfollows = "r0"\nl_m = {1 + i}\nphi_deg = 180.0\n'
        )
    return text + "".join(f'[[robots]]\nid = "r{i}"\n' for i in range(n))


# case: (file text, extra arguments, what the message must say)
CASES: dict[str, tuple[str | bytes, list[str], str]] = {
    "unknown key": (WEDGE_TEXT.replace("seed = 1", "seed = 1\nsed = 2"), [], "did you mean 'seed'"),
    "wrong type": (WEDGE_TEXT.replace("duration_s = 200.0", 'duration_s = "x"'), [], "duration_s"),
    "nan": (WEDGE_TEXT.replace("duration_s = 200.0", "duration_s = nan"), [], "finite number"),
    "syntax error": (WEDGE_TEXT.replace("seed = 1", "seed = = 1"), [], "not valid TOML"),
    "empty file": ("", [], "robots: Field required"),
    "binary file": (bytes(range(256)) * 4, [], "not a text file"),
    "follow cycle": (_cycle(), [], "is a cycle"),
    "10000 robots": (_many(10_000), [], "at most 1000"),
    "too many robot-steps": (WEDGE_TEXT.replace("duration_s = 200.0", "duration_s = 86400.0")
                             .replace("control_rate_hz = 10.0", "control_rate_hz = 100.0")
                             .replace('[[robots]]\nid = "r3"', '[[robots]]\nid = "r3"'),
                             ["--set", "duration_s=86400"], "robot-steps"),
    "--set nonsense": (WEDGE_TEXT, ["--set", "nonsense"], "expected PATH=VALUE"),
    "--set negative": (WEDGE_TEXT, ["--set", "limits.v_max_mps=-1"], "greater than 0"),
    "--set unknown": (WEDGE_TEXT, ["--set", "noexist.x=1"], "no field 'noexist'"),
    # Numbers past what physics allows: the first four once ended in a traceback (an
    # integer overflowed, or a run had no step), the rest ran as if they meant something.
    "a run of no step": (WEDGE_TEXT, ["--set", "duration_s=0.05"],
                         "shorter than one control period"),
    "a state older than the universe": (WEDGE_TEXT, ["--set", "comm_delay_s=1e300"],
                                        "less than or equal to 10"),
    "settling for ever": (WEDGE_TEXT, ["--set", "settle_s=1e300"], "less than or equal to 86400"),
    "backing off for ever": (WEDGE_TEXT, ["--set", "deadlock.safe_distance_m=1e300"],
                             "less than or equal to 1000000"),
    "a goal off the world": (WEDGE_TEXT, ["--set", "navigation.waypoints=[[1e300, 0]]"],
                             "less than or equal to 1000000"),
    "a slot a light year off": (WEDGE_TEXT.replace("l_m = 1.0", "l_m = 1e16", 1), [],
                                "less than or equal to 1000000"),
    "faster than any robot": (WEDGE_TEXT.replace("v_mps = 0.15", "v_mps = 150", 1), [],
                              "less than or equal to 10"),
}  # fmt: skip


def _write(tmp_path: Path, case: str, text: str | bytes) -> Path:
    path = tmp_path / (re.sub(r"\W+", "_", case) + ".toml")
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
@pytest.mark.parametrize("case", sorted(CASES))
def test_a_bad_file_or_value_is_one_message_and_exit_2(tmp_path: Path, case: str) -> None:
    text, extra, says = CASES[case]
    path = _write(tmp_path, case, text)
    argv = [*CLI, "run", str(path), "--no-recording", "--no-progress", *extra]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr + proc.stdout
    assert str(path) in proc.stderr  # the file
    assert says in proc.stderr  # the field and the fix
    assert len(proc.stderr.strip().splitlines()) <= 4, proc.stderr


def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    path = _write(tmp_path, "syntax", CASES["syntax error"][0])
    proc = subprocess.run([*CLI, "--debug", "run", str(path)], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip
    assert proc.returncode != 0
    assert "Traceback" in proc.stderr
    assert "ConfigError" in proc.stderr


def test_up_refuses_a_self_following_file_before_starting_anything(tmp_path: Path) -> None:
    text = WEDGE_TEXT.replace('robot = "r2"\nfollows = "r1"', 'robot = "r2"\nfollows = "r2"')
    path = _write(tmp_path, "self follow", text)
    out = tmp_path / "out"
    proc = subprocess.run([*CLI, "up", str(path), "--out", str(out), "--fleet", "selfie"],
                          capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr + proc.stdout
    assert "is a cycle" in proc.stderr
    assert str(path) in proc.stderr
    assert "recording:" not in proc.stdout  # nothing started, nothing announced
    assert not out.exists()


def test_a_bad_deployment_file_is_one_message_and_exit_2(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(
        'name = "bad"\nfleet = "bad"\nscenario = "nowhere.toml"\n'
        '[[hosts]]\nname = "h1"\naddress = "127.0.0.1"\n[[robots]]\nid = "r1"\nhost = "h11"\n'
    )
    proc = subprocess.run([*CLI, "status", str(path)], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert str(path) in proc.stderr
    assert "did you mean 'h1'" in proc.stderr


@pytest.mark.parametrize(
    ("old", "new", "says"),
    [
        (
            "v_max_mps = 1.2 ",
            "v_max_mps = 1e9 ",
            "v_max_mps: Input should be less than or equal to 10",
        ),
        ("min_range_m = 0.1", "min_range_m = 6.0", "min_range_m must be below max_range_m"),
    ],
    ids=["rated faster than any robot", "a sonar seeing from past its reach"],
)
def test_a_robot_file_past_physics_is_one_message_and_exit_2(
    tmp_path: Path, old: str, new: str, says: str
) -> None:
    rated = (CONFIG_ROOT / "robots" / "p3dx.toml").read_text()
    assert old in rated
    path = tmp_path / "robot.toml"
    path.write_text(rated.replace(old, new, 1))
    proc = subprocess.run([*CLI, "validate", str(path)], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr + proc.stdout
    assert says in proc.stdout + proc.stderr
