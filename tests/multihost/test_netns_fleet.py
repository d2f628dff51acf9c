"""A fleet across three hosts in network namespaces: world on one, agents on the others.

Each host runs `phalanx host` in its own namespace (IPv4 only, joined by a bridge); the
launcher runs in the world's namespace, as on the laptop. The lockstep run must give the
single-process metrics; in real time, pulling one host's cable must stop its robots and
plugging it back must bring them back.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from netlab import NetLab

from phalanx.analysis.metrics import run_metrics
from phalanx.core.config_files import apply_overrides, load_scenario
from phalanx.runtime.batch import run_batch

pytestmark = pytest.mark.integration
PORT = 7447  # every namespace has its own port space
DURATION_S = 115.0  # past the deadlock reverse at t = 100 s


def _write_deployment(kit: Any, lab: NetLab, tmp_path: Path, name: str, clock: str) -> Path:
    hosts = [(h, lab.address(h), PORT) for h in kit.LAB_HOSTS]
    text = kit.deployment_text(name=name, hosts=hosts, out_dir=tmp_path / "results", clock=clock)
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


@pytest.mark.timeout(260)  # its child processes' own bound, and set-up
def test_lockstep_across_namespaces_gives_the_single_host_metrics(
    kit: Any, lab: NetLab, tmp_path: Path, same_follower_metrics: Callable[..., None]
) -> None:
    deployment = _write_deployment(kit, lab, tmp_path, "nslock", "lockstep")
    daemons = kit.start_daemons(deployment, kit.LAB_HOSTS, tmp_path / "logs", wrap=lab.command)
    try:
        launched = subprocess.run(
            lab.command("world", [
                *kit.CLI, "launch", str(deployment), "--set", f"duration_s={DURATION_S}",
                "--run-id", "lock1", "--no-table", "--host-wait", "60", "--timeout", "150",
            ]),
            capture_output=True, text=True, timeout=200, check=False,
        )  # fmt: skip
    finally:
        codes = daemons.stop()
    context = launched.stdout[-3000:] + launched.stderr[-2000:] + daemons.log_tail()
    assert launched.returncode == 0, context
    assert "fleet up in" in launched.stdout, context
    assert codes == dict.fromkeys(kit.LAB_HOSTS, 0), context
    multi = json.loads((tmp_path / "results" / "lock1" / "metrics.json").read_text())
    scenario = apply_overrides(load_scenario(kit.WEDGE), [f"duration_s={DURATION_S}"])
    single = run_metrics(run_batch(scenario))
    same_follower_metrics(multi, single)
    assert multi["collisions"] == single["collisions"]


def _moving(records: list[dict[str, Any]], robots: tuple[str, ...], after: float) -> bool:
    """Every robot's body (the world's sense frame) moving after `after`."""
    return all(
        any(r["kind"] == "sense" and r["robot"] == rid and r["t"] > after and r["v"] > 0.05
            for r in records)
        for rid in robots
    )  # fmt: skip


def _stopped(records: list[dict[str, Any]], robots: tuple[str, ...], after: float) -> bool:
    """Every robot's body at rest after `after`."""
    return all(
        any(r["kind"] == "sense" and r["robot"] == rid and r["t"] > after and abs(r["v"]) < 0.005
            for r in records)
        for rid in robots
    )  # fmt: skip


def _alive(
    records: list[dict[str, Any]], robots: tuple[str, ...], after: float, *, alive: bool
) -> bool:
    return all(
        any(r["kind"] == "alive" and r["robot"] == rid and r["t"] > after and r["alive"] is alive
            for r in records)
        for rid in robots
    )  # fmt: skip


def _publishing(records: list[dict[str, Any]], robots: tuple[str, ...], after: float) -> bool:
    return all(
        any(r["kind"] == "state" and r["robot"] == rid and r["t"] > after for r in records)
        for rid in robots
    )


def test_a_host_that_loses_its_link_stops_its_robots_and_they_rejoin(
    kit: Any, lab: NetLab, tmp_path: Path
) -> None:
    """Pull robot-b's cable: the world stops r2 and r3 (their liveliness is gone after
    the 0.5 s lease); plug it back: the link is retried, r2 and r3 drive again."""
    deployment = _write_deployment(kit, lab, tmp_path, "nsreal", "realtime")
    daemons = kit.start_daemons(deployment, kit.LAB_HOSTS, tmp_path / "logs", wrap=lab.command)
    far = ("r2", "r3")
    launcher = observer = None
    try:
        with (tmp_path / "launch.log").open("wb") as sink:
            launcher = subprocess.Popen(
                lab.command("world", [
                    *kit.CLI, "launch", str(deployment), "--set", "duration_s=60",
                    "--run-id", "real1", "--no-table", "--host-wait", "60", "--timeout", "120",
                ]),
                stdout=sink, stderr=subprocess.STDOUT,
            )  # fmt: skip
        observer = kit.Observer(lab.command("world", [
            kit.PYTHON, kit.NETLAB, "observe", "--fleet", "nsreal",
            "--connect", f"tcp/127.0.0.1:{PORT}", "--seconds", "120",
        ]))  # fmt: skip

        def context() -> str:
            return (tmp_path / "launch.log").read_text()[-3000:] + daemons.log_tail(1500)

        assert observer.wait_for(lambda rs: _moving(rs, far, 0.0), 60.0), context()

        lab.set_link("robot-b", up=False)
        pulled = time.monotonic()
        gone = observer.wait_for(lambda rs: _alive(rs, far, pulled, alive=False), 5.0)
        assert gone is not None, f"the world never noticed robot-b's loss\n{context()}"
        stopped = observer.wait_for(lambda rs: _stopped(rs, far, pulled), 5.0)
        assert stopped is not None, f"r2/r3 kept moving\n{context()}"
        # The world commands zero from the moment it notices (the lease, 0.5 s); the bodies
        # then brake at the P3DX's 0.3 m/s^2: at most 1 s from the 0.3 m/s bound.
        assert gone - pulled < 1.5, f"loss noticed after {gone - pulled:.2f} s"
        assert stopped - gone < 1.6, f"at rest {stopped - gone:.2f} s after the loss was noticed"

        lab.set_link("robot-b", up=True)
        plugged = time.monotonic()
        back = observer.wait_for(lambda rs: _alive(rs, far, plugged, alive=True), 15.0)
        assert back is not None, f"r2/r3 never came back\n{context()}"
        moving = observer.wait_for(
            lambda rs: _moving(rs, far, plugged) and _publishing(rs, far, plugged), 15.0
        )
        assert moving is not None, f"r2/r3 came back but do not drive\n{context()}"
        assert back - plugged < 5.0, f"rejoined {back - plugged:.2f} s after the link returned"

        launcher.send_signal(signal.SIGINT)  # Ctrl-C: the launcher stops the fleet
        assert launcher.wait(40) == 1  # interrupted
        log = (tmp_path / "launch.log").read_text()
        assert "robot-b: host lost" in log or "r2 on robot-b: host lost" in log, log[-3000:]

        status = subprocess.run(
            lab.command("robot-a", [
                *kit.CLI, "status", str(deployment), "--json", "--listen-s", "0.5",
            ]),
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert status.returncode == 0, status.stdout[-2000:] + status.stderr[-2000:]
        hosts = json.loads(status.stdout)["hosts"]
        states = [c["state"] for h in hosts.values() for c in h["children"]]
        assert states, hosts
        assert set(states) <= {"stopped", "finished"}, states
    finally:
        if launcher is not None and launcher.poll() is None:
            launcher.kill()
            launcher.wait(5)
        if observer is not None:
            observer.close()
        codes = daemons.stop()
    assert codes == dict.fromkeys(kit.LAB_HOSTS, 0), daemons.log_tail()
