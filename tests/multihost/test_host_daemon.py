"""Host daemons on loopback (no root needed): requests checked and refused, crashed agents
restarted with back-off, children's output streamed, `phalanx stop`, missing hosts named."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from fleetlab import wait_for

from phalanx.hosts.children import ManagedChild
from phalanx.hosts.daemon import DaemonOptions, HostDaemon
from phalanx.hosts.deployment import load_deployment
from phalanx.hosts.fleet_client import FleetClient
from phalanx.hosts.protocol import ChildStatus, HostStatus, LogLine
from phalanx.hosts.wiring import client_transport
from phalanx.wire.keys import alive_key
from phalanx.wire.transport import free_tcp_port

pytestmark = pytest.mark.integration
PLACEMENT = {"r1": "h1", "r2": "h2", "r3": "h2"}


def _deployment(kit: Any, tmp_path: Path, name: str, *, zenoh_extra: str = "") -> Path:
    hosts = [("h1", "127.0.0.1", free_tcp_port()), ("h2", "127.0.0.1", free_tcp_port())]
    text = kit.deployment_text(
        name=name, hosts=hosts, out_dir=tmp_path / "results", clock="realtime",
        placement=PLACEMENT, world_host="h1", lease_ms=1000, zenoh_extra=zenoh_extra,
    )  # fmt: skip
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def _child(status: HostStatus | None, name: str) -> ChildStatus | None:
    if status is None:
        return None
    return next((c for c in status.children if c.name == name), None)


def test_bad_requests_are_refused_with_a_reason_and_counted(kit: Any, tmp_path: Path) -> None:
    path = _deployment(kit, tmp_path, "refuse")
    loaded = load_deployment(path)
    good = {"deployment": "refuse", "digest": loaded.digest, "run_id": "run1"}
    bad: list[tuple[bytes, str]] = [
        (b"", "malformed spawn request"),
        (b"{not json", "malformed spawn request"),
        (b"\xff\xfe" * 10, "malformed spawn request"),
        (json.dumps({**good, "command": "rm -rf /"}).encode(), "Extra inputs are not permitted"),
        (json.dumps({**good, "version": 2}).encode(), "version"),
        (json.dumps({**good, "run_id": "../../etc"}).encode(), "run_id"),
        (json.dumps({**good, "overrides": ["duration_s=1\n--driver=x"]}).encode(), "overrides"),
        (json.dumps({**good, "epoch_unix": float("nan")}).encode(), "epoch_unix"),
        (json.dumps({**good, "deployment": "other"}).encode(), "serves deployment 'refuse'"),
        (json.dumps({**good, "digest": "0" * 64}).encode(), "differs on host"),
        (json.dumps({**good, "robots": ["rr2"]}).encode(), "did you mean 'r2'"),
        (json.dumps({**good, "robots": ["r1"]}).encode(), "runs on host 'h1'"),
        (json.dumps({**good, "overrides": ["duration_s=-5"]}).encode(), "duration_s"),
        (json.dumps({**good, "epoch_unix": 1.0}).encode(), "more than a day"),
        (b" " * (65 * 1024), "at most"),
    ]
    daemons = kit.start_daemons(path, ["h1", "h2"], tmp_path / "logs")
    try:
        with FleetClient(loaded, client_transport(loaded.spec, via="h1")) as client:
            client.wait_for_hosts(30.0, lambda _text: None)
            for payload, reason in bad:
                reply = client.ask("spawn", {"h2": payload}, timeout_s=5.0)["h2"]
                assert reply is not None, payload[:60]
                assert not reply.ok, payload[:60]
                assert reason in reply.error, (payload[:60], reply.error)
            stop = {"deployment": "refuse", "digest": loaded.digest, "run_id": "nope"}
            stop_reply = client.ask("stop", {"h2": json.dumps(stop).encode()})
            assert stop_reply["h2"] is not None
            assert "not this host's" in stop_reply["h2"].error
            # r2 is already on the fabric (an orphan, or started elsewhere): never twice.
            client.session.declare_alive(alive_key("refuse", "r2"))
            time.sleep(0.5)
            twice = client.ask("spawn", {"h2": json.dumps({**good, "robots": ["r2"]}).encode()})
            assert twice["h2"] is not None
            assert "r2 is already on the fabric" in twice["h2"].error
            status = client.statuses()["h2"]
            assert status is not None
            assert status.refused == len(bad) + 2
            assert status.children == ()  # nothing was started
    finally:
        codes = daemons.stop()
    assert codes == {"h1": 0, "h2": 0}, daemons.log_tail()


def test_a_crashed_agent_restarts_with_backoff_and_the_output_reaches_the_launcher(
    kit: Any, tmp_path: Path
) -> None:
    path = _deployment(kit, tmp_path, "crash")
    loaded = load_deployment(path)
    daemons = kit.start_daemons(path, ["h1", "h2"], tmp_path / "logs")
    try:
        with FleetClient(loaded, client_transport(loaded.spec)) as client:
            client.wait_for_hosts(30.0, lambda _text: None)
            client.spawn("crash1", overrides=("duration_s=60",), epoch_unix=None)

            def r2() -> ChildStatus | None:
                return _child(client.statuses(["h2"])["h2"], "r2")

            def running() -> bool:
                statuses = client.statuses()
                world, agent = _child(statuses["h1"], "world"), _child(statuses["h2"], "r2")
                return all(c is not None and c.state == "running" for c in (world, agent))

            assert wait_for(running, 40.0, poll_s=0.1), daemons.log_tail()
            time.sleep(0.5)  # the world has subscribed to the robots' liveliness
            first = r2()
            assert first is not None
            assert first.pid is not None
            os.kill(first.pid, signal.SIGKILL)
            assert wait_for(
                lambda: (c := r2()) is not None and c.restarts == 1 and c.state == "running",
                30.0,
                poll_s=0.1,
            ), daemons.log_tail()
            again = r2()
            assert again is not None
            assert again.pid != first.pid
            assert "killed by SIGKILL" in again.last_error

            def heard(line: LogLine) -> bool:
                return line.host == "h1" and line.child == "world" and "r2 is gone" in line.line

            lines: list[LogLine] = []

            def world_said_r2_gone() -> bool:
                while not client.watch.logs.empty():
                    lines.append(client.watch.logs.get())
                return any(heard(line) for line in lines)

            assert wait_for(world_said_r2_gone, 10.0, poll_s=0.1), [line.line for line in lines][
                -20:
            ]

        stopped = subprocess.run(
            [*kit.CLI, "stop", str(path), "--wait", "20"],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
        assert "host h2: stopping" in stopped.stdout
        with FleetClient(loaded, client_transport(loaded.spec)) as client:
            states = {c.name: c.state for s in client.statuses().values() if s for c in s.children}
        # An agent may end by itself first: the stopped world sends its final frames.
        assert set(states) == {"r1", "world", "r2", "r3"}, states
        assert set(states.values()) <= {"stopped", "finished"}, states
        assert states["world"] == "stopped", states
    finally:
        codes = daemons.stop()
    assert codes == {"h1": 0, "h2": 0}, daemons.log_tail()


def test_launch_names_the_hosts_that_are_missing(kit: Any, tmp_path: Path) -> None:
    path = _deployment(kit, tmp_path, "missing")
    daemons = kit.start_daemons(path, ["h1"], tmp_path / "logs")
    try:
        launched = subprocess.run(
            [*kit.CLI, "launch", str(path), "--host-wait", "3", "--no-table"],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
    finally:
        codes = daemons.stop()
    assert launched.returncode == 2, launched.stdout + launched.stderr
    assert "hosts not present after 3 s: h2" in launched.stderr
    assert "phalanx host" in launched.stderr
    assert codes == {"h1": 0}


def test_ctrl_c_while_launch_waits_for_its_hosts_stops_it(kit: Any, tmp_path: Path) -> None:
    path = _deployment(kit, tmp_path, "waiting")
    daemons = kit.start_daemons(path, ["h1"], tmp_path / "logs")
    try:
        launcher = subprocess.Popen(
            [*kit.CLI, "launch", str(path), "--host-wait", "120", "--no-table"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            assert launcher.stdout is not None
            first = launcher.stdout.readline()  # printed once the signal handlers are in
            assert "launching" in first, first
            time.sleep(1.0)  # into the wait for h2, which never comes
            started = time.monotonic()
            launcher.send_signal(signal.SIGINT)
            out, err = launcher.communicate(timeout=20)
            stopped_s = time.monotonic() - started
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.communicate()
    finally:
        codes = daemons.stop()
    assert launcher.returncode == 1, first + out + err
    assert "interrupted while waiting for the hosts" in out, out + err
    assert stopped_s < 10.0, stopped_s  # not the 120 s of --host-wait
    assert codes == {"h1": 0}


def test_hosts_that_only_reach_a_router_find_each_other_through_it(
    kit: Any, tmp_path: Path
) -> None:
    port = free_tcp_port()
    path = _deployment(
        kit, tmp_path, "hub", zenoh_extra=f'router = {{ address = "127.0.0.1", port = {port} }}'
    )
    loaded = load_deployment(path)
    with (tmp_path / "router.log").open("wb") as sink:
        router = subprocess.Popen(
            [*kit.CLI, "router", str(path)], stdout=sink, stderr=subprocess.STDOUT
        )
    daemons = kit.start_daemons(path, ["h1", "h2"], tmp_path / "logs")
    try:
        # Through h1's daemon, h2 answers: h1 -> router -> h2 (neither connects to the other).
        with FleetClient(loaded, client_transport(loaded.spec, via="h1")) as client:
            statuses = client.wait_for_hosts(30.0, lambda _text: None)
            assert set(statuses) == {"h1", "h2"}
            assert statuses["h2"].robots == ("r2", "r3")
    finally:
        codes = daemons.stop()
        router.send_signal(signal.SIGTERM)
        router_code = router.wait(15)
    assert codes == {"h1": 0, "h2": 0}, daemons.log_tail()
    assert router_code == 0
    assert f"router listening on tcp/127.0.0.1:{port}" in (tmp_path / "router.log").read_text()


def _bare_daemon(grace_s: float) -> HostDaemon:
    """A daemon without a session: its supervision alone, on children we give it."""
    return HostDaemon(load_deployment("loopback"), "robot-b", DaemonOptions(grace_s=grace_s))


def _adopt(daemon: HostDaemon, name: str, code: str) -> ManagedChild:
    """Supervise `python -c code` as agent `name` (only a test may run such a child)."""
    child = ManagedChild(
        name,
        "agent",
        [sys.executable, "-c", code],
        policy=daemon.spec.restart,
        on_line=lambda *_: None,
    )
    daemon.children[name] = child
    child.start(workdir=Path.cwd())
    return child


def test_a_child_that_ignores_sigterm_is_killed_after_the_grace_period() -> None:
    daemon = _bare_daemon(grace_s=0.5)
    stubborn = _adopt(
        daemon,
        "r2",
        "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
        "print('up', flush=True); time.sleep(60)",
    )
    assert wait_for(lambda: "up" in stubborn.lines, 10.0, poll_s=0.1)
    started = time.monotonic()
    daemon.shutdown()
    assert stubborn.poll() == -signal.SIGKILL
    assert 0.5 <= time.monotonic() - started < 5.0
    assert stubborn.state == "stopped"


def test_a_crash_is_reported_with_its_last_error_and_restarted_after_a_delay() -> None:
    daemon = _bare_daemon(grace_s=0.5)
    crashing = _adopt(
        daemon,
        "r3",
        "import sys; print('starting'); print('ERROR no robot', flush=True); sys.exit(3)",
    )
    assert wait_for(lambda: (daemon.supervise(), crashing.state)[1] == "backoff", 10.0, poll_s=0.1)
    assert crashing.last_error == "exit 3: ERROR no robot"
    assert crashing.restart_at - time.monotonic() <= daemon.spec.restart.backoff_s
    assert wait_for(lambda: (daemon.supervise(), crashing.restarts)[1] == 1, 10.0, poll_s=0.1)
    daemon.shutdown()
    assert crashing.poll() is not None
