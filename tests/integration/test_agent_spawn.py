"""Agents started from their spec, as `phalanx up` and the host daemons start them: the
spec on the agent's standard input at every start, and the runtime's factory building a
running agent from a spec alone."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.hosts.children import ManagedChild
from phalanx.hosts.deployment import RestartPolicy, load_deployment
from phalanx.hosts.wiring import RunParameters, agent_spec
from phalanx.runtime.agent_process import run_agent
from phalanx.runtime.exits import EXIT_WORLD_LOST
from phalanx.runtime.local_fleet import UpOptions, plan
from phalanx.runtime.process_spec import AgentSpec, spawn_argv
from phalanx.runtime.signals import SignalStop
from phalanx.wire.transport import TransportConfig, free_tcp_port, loopback_endpoint

pytestmark = pytest.mark.integration
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


def _wait(child: ManagedChild, timeout_s: float = 60.0) -> int:
    deadline = time.monotonic() + timeout_s
    while (code := child.poll()) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert code is not None, f"{child.name} did not end"
    child.join_output(5.0)
    return code


def test_a_daemons_agent_reads_its_spec_at_every_start() -> None:
    spec = agent_spec(load_deployment("loopback"), "r2", run=RunParameters("run1"))
    lines: list[str] = []
    child = ManagedChild(
        "r2", "agent", [*spawn_argv(spec, python=sys.executable), "--print-spec"],
        policy=RestartPolicy(), on_line=lambda _c, line, _l: lines.append(line), spec=spec,
    )  # fmt: skip
    for _start in range(2):  # a restart hands it the same spec again
        lines.clear()
        child.start(workdir=Path.cwd())
        assert _wait(child) == 0, lines
        assert AgentSpec.model_validate_json("\n".join(lines)) == spec


def test_up_hands_each_agent_its_spec(capfd: pytest.CaptureFixture[str]) -> None:
    *_, agent = plan(WEDGE, load_scenario(WEDGE), UpOptions(fleet="spawned", pin=False))
    assert agent.spec is not None
    agent.argv.append("--print-spec")
    agent.start()
    assert agent.process is not None
    assert agent.process.wait(60) == 0
    assert AgentSpec.model_validate_json(capfd.readouterr().out) == agent.spec


def test_the_factory_runs_a_simulated_agent_from_its_spec_alone() -> None:
    # No world on its fleet: the agent runs, hears no frame and says so by its exit code.
    spec = AgentSpec(
        scenario=WEDGE,
        robot_id="r2",
        fleet="factory-alone",
        transport=TransportConfig(listen=(loopback_endpoint(free_tcp_port()),)),
        frame_timeout_s=1.0,
    )
    started = time.monotonic()
    report, code = run_agent(spec, stop=SignalStop())
    assert code == EXIT_WORLD_LOST
    assert report.robot_id == "r2"
    assert report.steps == 0
    assert time.monotonic() - started < 30.0
