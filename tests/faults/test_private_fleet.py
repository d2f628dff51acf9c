"""A private local fleet (issue 47, row 5): `phalanx up` talks over a Unix-domain socket in
a directory only its user can open, and over nothing else.

The fleet under test is a real `phalanx up` (the paper wedge in real time); its endpoint
is read from the world's command line, as an attacker on the machine would. The same
user's client joins through the socket; the fleet's processes listen on no TCP port; a
process of another user (uid 65534) cannot open a Zenoh session to the socket, and a
forged leader state it sends is never heard, while the same program run as the fleet's
user is heard (so the test can see a forgery that gets through).

The other user's process starts as root and drops to uid/gid 65534 (no supplementary
groups, no way back) after loading its modules and before opening any socket: the
interpreter here lives under a home directory that uid 65534 may not enter, so the drop
cannot happen before `exec` (`preexec_fn`).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from fleetlab import CLI, WEDGE, child_running, children_of, cmdline, wait_for

from phalanx.core.errors import TransportError
from phalanx.runtime.local_fleet import private_fabric
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import RobotState
from phalanx.wire.transport import TransportConfig, open_session, unix_socket_endpoint

pytestmark = pytest.mark.slow
FLEET = "private"
NOBODY = 65534
UNIXSOCK = "unixsock-stream/"

# Forges r1's (the leader's) state at x = MARKER; optionally drops to uid/gid 65534 first.
# Prints what happened as JSON; exit 3 when the session could not be opened.
FORGER = """
import json, os, sys, time
import zenoh
from phalanx.wire.codec import encode
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import RobotState
from phalanx.wire.transport import TransportConfig, zenoh_config

endpoint, fleet, marker, uid = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
conf = zenoh_config(TransportConfig(mode="client", connect=(endpoint,), lowlatency=True))
payload = encode(RobotState(
    robot_id="r1", seq=10**6, stamp_s=1.0, x_m=marker, y_m=0.0, theta_rad=0.0,
    v_mps=0.0, omega_radps=0.0, fsm_state="NAVIGATE",
))
if uid != os.geteuid():
    os.setgroups([])
    os.setgid(uid)
    os.setuid(uid)
report = {"uid": os.geteuid(), "gid": os.getegid()}
try:
    os.stat(endpoint.split("/", 1)[1])
    report["stat"] = "ok"
except OSError as exc:
    report["stat"] = type(exc).__name__
try:
    session = zenoh.open(conf)
except Exception as exc:
    report["open"] = "refused: " + str(exc)[:300]
    print(json.dumps(report), flush=True)
    sys.exit(3)
for _ in range(40):
    session.put(robot_key(fleet, "r1", "state"), payload)
    time.sleep(0.025)
session.close()
report["open"] = "ok"
print(json.dumps(report), flush=True)
"""


@dataclass
class Heard:
    """The x of every r1 state the fleet's router passed on to a same-user client."""

    xs: list[float] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_state(self, _key: str, state: RobotState) -> None:
        with self.lock:
            self.xs.append(state.x_m)

    def saw(self, x_m: float) -> bool:
        with self.lock:
            return x_m in self.xs


@dataclass
class UpFleet:
    """A running `phalanx up`: its process, its world's pid and the world's endpoint."""

    up: subprocess.Popen[bytes]
    world: int
    endpoint: str
    log: Path

    def pids(self) -> list[int]:
        """`up` and every process it started."""
        return [self.up.pid, *children_of(self.up.pid)]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[UpFleet]:
    workdir = tmp_path_factory.mktemp("private")
    log = workdir / "up.log"
    with log.open("wb") as sink:
        up = subprocess.Popen(
            [*CLI, "up", str(WEDGE), "--fleet", FLEET, "--clock", "realtime",
             "--set", "duration_s=60", "--timeout", "90", "--no-recording",
             "--out", str(workdir / "out")],
            stdout=sink, stderr=subprocess.STDOUT,
        )  # fmt: skip
    try:
        assert wait_for(lambda: child_running(up.pid, "world") is not None, 30.0), _tail(log)
        world = child_running(up.pid, "world")
        assert world is not None
        argv = cmdline(world)
        running = UpFleet(up, world, argv[argv.index("--listen") + 1], log)
        with _listening(running) as heard:  # (the fleet is up: r1 publishes)
            assert wait_for(lambda: len(heard.xs) >= 1, 30.0), _tail(log)
        yield running
    finally:
        if up.poll() is None:
            up.send_signal(signal.SIGTERM)
        try:
            up.wait(30)
        except subprocess.TimeoutExpired:
            up.kill()
            up.wait(10)


def _tail(log: Path) -> str:
    return log.read_text(errors="replace")[-2000:] if log.exists() else ""


def _socket_path(endpoint: str) -> Path:
    assert endpoint.startswith(UNIXSOCK), f"the fleet listens on {endpoint}, not a socket"
    return Path(endpoint.removeprefix(UNIXSOCK))


def _tcp_listening(pid: int) -> list[str]:
    """The TCP sockets `pid` listens on, as `address:port` in hex (from /proc)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        with_inode = re.fullmatch(r"socket:\[(\d+)\]", _readlink(fd))
        if with_inode:
            inodes.add(with_inode.group(1))
    found = []
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # 0A: LISTEN
                found.append(fields[1])
    return found


def _readlink(fd: Path) -> str:
    try:
        return os.readlink(fd)
    except OSError:  # closed meanwhile
        return ""


def _forge(fleet: UpFleet, marker_x_m: float, uid: int) -> tuple[int, dict[str, object]]:
    """Run FORGER against the fleet as `uid`; its exit code and report."""
    done = subprocess.run(
        [sys.executable, "-c", FORGER, fleet.endpoint, FLEET, str(marker_x_m), str(uid)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    lines = done.stdout.strip().splitlines()
    assert lines, done.stderr[-2000:]
    return done.returncode, json.loads(lines[-1])


@contextmanager
def _listening(fleet: UpFleet) -> Iterator[Heard]:
    """A same-user client of the fleet hearing r1's states."""
    heard = Heard()
    cfg = TransportConfig(mode="client", connect=(fleet.endpoint,), lowlatency=True)
    with open_session(cfg) as session:
        session.subscribe(robot_key(FLEET, "r1", "state"), RobotState, heard.on_state)
        yield heard


def test_the_fleet_listens_on_a_socket_in_a_private_directory_and_on_no_tcp_port(
    fleet: UpFleet,
) -> None:
    path = _socket_path(fleet.endpoint)
    folder = path.parent
    info = folder.lstat()
    assert stat.S_ISDIR(info.st_mode)
    assert stat.S_IMODE(info.st_mode) == 0o700  # only its user (and root) may open it
    assert info.st_uid == os.geteuid()
    assert stat.S_ISSOCK(path.lstat().st_mode)
    assert sorted(p.name for p in folder.iterdir() if p.name != f"{path.name}.lock") == [path.name]
    pids = fleet.pids()
    assert len(pids) == 5, [cmdline(p) for p in pids]  # up, the world and three agents
    for pid in pids:
        assert _tcp_listening(pid) == [], cmdline(pid)
        argv = cmdline(pid)
        for flag in ("--listen", "--connect"):
            if flag in argv:
                assert argv[argv.index(flag) + 1] == fleet.endpoint, argv
    # The same user, given the path, joins: the socket is the way in, its folder the lock.
    with _listening(fleet) as heard:
        assert wait_for(lambda: len(heard.xs) >= 5, 20.0), _tail(fleet.log)


@pytest.mark.skipif(
    os.geteuid() != 0, reason="starting a process as another user (uid 65534) needs root"
)
def test_another_user_can_neither_join_nor_forge_a_leader_state(fleet: UpFleet) -> None:
    with _listening(fleet) as heard:
        assert wait_for(lambda: len(heard.xs) >= 1, 20.0), _tail(fleet.log)
        code, report = _forge(fleet, 71.5, NOBODY)
        assert (report["uid"], report["gid"]) == (NOBODY, NOBODY)
        # The same program as the fleet's own user is heard, after the other user's
        # attempt: had that forgery got through, it would have been seen first.
        mine_code, mine = _forge(fleet, 72.5, os.geteuid())
        assert (mine_code, mine["open"]) == (0, "ok"), mine
        assert wait_for(lambda: heard.saw(72.5), 10.0)
        assert not heard.saw(71.5), report
        assert code == 3, report
        assert str(report["open"]).startswith("refused"), report
        assert report["stat"] == "PermissionError"  # the directory is closed to it
    assert fleet.up.poll() is None, _tail(fleet.log)  # the fleet ran on throughout


def test_the_private_directory_is_made_per_run_and_removed_after_it() -> None:
    with private_fabric() as first, private_fabric() as second:
        folders = [_socket_path(first).parent, _socket_path(second).parent]
        assert folders[0] != folders[1]
        for folder in folders:
            assert stat.S_IMODE(folder.lstat().st_mode) == 0o700
        (folders[0] / "left-behind").write_bytes(b"x")
    assert not any(folder.exists() for folder in folders)


@pytest.mark.timeout(240)  # its child processes' own bound, and set-up
def test_up_runs_to_completion_over_the_socket_and_leaves_no_directory(tmp_path: Path) -> None:
    done = subprocess.run(
        [*CLI, "up", str(WEDGE), "--fleet", "private-lockstep", "--set", "duration_s=5",
         "--timeout", "120", "--no-recording", "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    found = re.search(r"the fleet's Zenoh endpoint: (\S+)", done.stderr)
    assert found is not None, done.stderr[-2000:]
    folder = _socket_path(found.group(1)).parent
    assert folder.name.startswith("phalanx-fleet-")
    assert not folder.exists()


def test_a_runtime_directory_others_may_open_or_a_long_path_is_passed_over(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    shared.chmod(0o755)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(shared))
    deep = tmp_path / ("d" * 100)
    deep.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(deep))  # (a TMPDIR too long for a socket)
    with private_fabric() as endpoint:
        assert _socket_path(endpoint).parent.parent == Path("/tmp")
    assert list(shared.iterdir()) == []
    # (a runtime directory with a short path, as /run/user/<uid> is: the test's own
    # folder can be too deep for a socket in it, as it is in a pytest-xdist worker)
    own = Path(tempfile.mkdtemp(prefix="xdg-", dir="/tmp"))  # (mode 0700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(own))
    try:
        with private_fabric() as endpoint:
            assert _socket_path(endpoint).parent.parent == own
        assert list(own.iterdir()) == []
    finally:
        shutil.rmtree(own)
    with pytest.raises(TransportError, match="at most 103 bytes"):
        unix_socket_endpoint(deep / "zenoh.sock")
