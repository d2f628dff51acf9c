"""Fixtures shared by every test tier: no test may leak a child process or a session."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from phalanx.transport import open_session_count

REPO = Path(__file__).resolve().parent.parent
SCENARIOS = REPO / "configs" / "scenarios"


def _children() -> set[int]:
    pids: set[int] = set()
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        try:
            text = (task / "children").read_text().split()
        except FileNotFoundError:
            continue  # a thread that ended while we looked
        pids.update(int(p) for p in text)
    return pids


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


@pytest.fixture(autouse=True)
def _no_leaked_processes() -> Iterator[None]:
    before = _children()
    yield
    leaked = {pid for pid in _children() - before if _alive(pid)}
    if leaked:
        for pid in leaked:
            os.kill(pid, 9)
        pytest.fail(f"test leaked child processes {sorted(leaked)}")


@pytest.fixture(autouse=True)
def _no_leaked_sessions() -> Iterator[None]:
    before = open_session_count()
    yield
    leaked = open_session_count() - before
    if leaked:
        pytest.fail(f"test leaked {leaked} Zenoh session(s)")
