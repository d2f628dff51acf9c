"""An agent's spec: one value for everything its process runs with, read back as written,
checked by the driver registry, the only thing `phalanx up` and the host daemons hand an
agent, and what the runtime's factory builds it from."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import pytest
import typer.main
from pydantic import ValidationError
from typer.testing import CliRunner

from phalanx.cli import app
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.errors import ConfigError
from phalanx.drivers import BACKENDS, settings_from_options, settings_model
from phalanx.drivers.arcos import ArcosSettings
from phalanx.runtime.agent_process import agent_scenario
from phalanx.runtime.local_fleet import UpOptions, plan
from phalanx.runtime.process_spec import (
    MAX_SPEC_BYTES,
    AgentSpec,
    DriverChoice,
    TelemetryTarget,
    driver_choice,
    read_spec,
    spawn_argv,
)
from phalanx.wire.security import TlsFiles
from phalanx.wire.transport import TransportConfig

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
ENDPOINT = "unixsock-stream//run/phalanx-fleet-test/zenoh.sock"


def _on_arcos() -> AgentSpec:
    return AgentSpec(
        scenario=WEDGE,
        overrides=("duration_s=12", 'controller.kind="ours"'),
        robot_id="r2",
        fleet="lab",
        clock="realtime",
        transport=TransportConfig(
            mode="client",
            connect=("tls/127.0.0.1:7447",),
            tls=TlsFiles(ca="/pki/ca.crt", cert="/pki/robot.r2.crt", key="/pki/robot.r2.key"),
        ),
        driver=DriverChoice(
            name="arcos", settings={"tcp": "127.0.0.1:8101", "place_at": [1, 2, 90]}
        ),
        epoch_s=1_700_000_000.125,
        watchdog_s=0.4,
        camera="/dev/video0=cam.toml",
        telemetry=TelemetryTarget(recording_id="run-1", file=Path("/out/r2.rrd"), url=None),
    )


def test_a_spec_reads_back_as_it_was_written(tmp_path: Path) -> None:
    spec = _on_arcos()
    assert spec.driver.settings == ArcosSettings(tcp="127.0.0.1:8101", place_at=(1.0, 2.0, 90.0))
    path = tmp_path / "r2.json"
    path.write_bytes(spec.encoded())
    assert read_spec(path) == spec
    assert read_spec(Path("-"), stdin=io.StringIO(spec.encoded().decode())) == spec
    simulated = AgentSpec(scenario=WEDGE, robot_id="r1")
    assert simulated.driver == DriverChoice(name="sim", settings=None)
    assert AgentSpec.model_validate_json(simulated.encoded()) == simulated


def test_a_spec_that_is_wrong_says_where(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text("{not json")
    with pytest.raises(ConfigError, match=r"agent spec .*bad.json: cannot read it as JSON"):
        read_spec(path)
    path.write_text('{"scenario": "w.toml", "robot_id": "r1", "flet": "x"}')
    with pytest.raises(ConfigError, match=r"flet: Extra inputs .*\(did you mean 'fleet'\?\)"):
        read_spec(path)
    path.write_text('{"scenario": "w.toml", "robot_id": "r1", "driver": {"name": "arcs"}}')
    with pytest.raises(ConfigError, match=r"got 'arcs' \(did you mean 'arcos'\?\)"):
        read_spec(path)
    with pytest.raises(ConfigError, match=r"bauds: Extra inputs .*did you mean 'baud'"):
        DriverChoice(name="arcos", settings={"port": "/dev/ttyS0", "bauds": 1})
    with pytest.raises(ConfigError, match="the sim driver has no settings"):
        DriverChoice(name="sim", settings={"port": "/dev/ttyS0"})
    with pytest.raises(ValidationError, match="telemetry needs --recording-id"):
        TelemetryTarget(url="rerun+http://127.0.0.1:9876/proxy")


def test_a_spec_too_large_is_refused_unread() -> None:
    huge = io.StringIO('{"scenario": "w.toml", "robot_id": "' + "r" * (MAX_SPEC_BYTES + 8) + '"}')
    with pytest.raises(ConfigError, match=r"agent spec standard input: .*over \d+ bytes"):
        read_spec(Path("-"), stdin=huge)
    assert huge.tell() == MAX_SPEC_BYTES + 1  # no more was read than the bound and a byte


def test_the_registry_says_whose_each_backend_option_is() -> None:
    agent = typer.main.get_command(app).commands["agent"]  # type: ignore[attr-defined]
    spelled = {o for p in agent.params for o in p.opts}
    for name, entry in BACKENDS.items():
        fields = settings_model(name).model_fields
        for option, field in entry.options:
            assert option in spelled, option  # `phalanx agent` has it
            assert field in fields, (name, field)  # and it sets one of the backend's settings
    given = {"--arcos-tcp": "h:1", "--baud": 19200, "--can-channel": None}
    assert settings_from_options("arcos", given) == {"tcp": "h:1", "baud": 19200}
    with pytest.raises(ConfigError, match="--arcos-tcp is an option of --driver arcos, not sim"):
        settings_from_options("sim", given)
    with pytest.raises(ConfigError, match="'tcp' given twice"):
        driver_choice("arcos", options=given, settings={"tcp": "h:2"})


def _agent(*argv: str, stdin: str | None = None) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["agent", *argv], input=stdin)
    return result.exit_code, " ".join(result.output.split())


def test_with_a_spec_the_agent_takes_no_other_option_but_its_own_names(tmp_path: Path) -> None:
    spec = _on_arcos()
    path = tmp_path / "r2.json"
    path.write_bytes(spec.encoded())
    code, shown = _agent("--robot", "r2", "--fleet", "lab", "--spec", str(path), "--print-spec")
    assert code == 0, shown
    assert AgentSpec.model_validate_json(shown) == spec
    code, shown = _agent("--spec", "-", "--print-spec", stdin=spec.encoded().decode())
    assert code == 0, shown
    assert AgentSpec.model_validate_json(shown) == spec
    for extra, said in (
        (["--robot", "r1"], "--robot r1: the spec's robot is r2"),
        (["--fleet", "default"], "--fleet default: the spec's fleet is lab"),
        (["--set", "seed=3", "--clock", "lockstep"], "leave out --set, --clock"),
        ([str(WEDGE)], "leave out SCENARIO"),
    ):
        code, shown = _agent(*extra, "--spec", str(path))
        assert code == 2, shown
        assert said in shown, shown


def test_the_options_make_the_same_spec_as_the_spec_they_print() -> None:
    code, shown = _agent(
        str(WEDGE), "--robot", "r2", "--fleet", "lab", "--clock", "realtime", "--mode",
        "client", "--connect", "tls/127.0.0.1:7447", "--tls-ca", "/pki/ca.crt",
        "--tls-cert", "/pki/robot.r2.crt", "--tls-key", "/pki/robot.r2.key",
        "--set", "duration_s=12", "--set", 'controller.kind="ours"', "--driver", "arcos",
        "--arcos-tcp", "127.0.0.1:8101", "--driver-setting", "place_at=[1, 2, 90]",
        "--epoch", "1700000000.125", "--watchdog", "0.4", "--camera", "/dev/video0=cam.toml",
        "--recording-id", "run-1", "--telemetry-file", "/out/r2.rrd", "--print-spec",
    )  # fmt: skip
    assert code == 0, shown
    assert AgentSpec.model_validate_json(shown) == _on_arcos()


def test_up_hands_every_agent_a_spec_and_no_options(tmp_path: Path) -> None:
    scenario = load_scenario(WEDGE)
    options = UpOptions(
        fleet="f", clock="realtime", out=tmp_path, driver="arcos", overrides=("duration_s=5",)
    )
    world, *rest = plan(WEDGE, scenario, options, endpoint=ENDPOINT)
    emulators, agents = rest[:3], rest[3:]
    assert [a.name for a in agents] == ["r1", "r2", "r3"]
    world_epoch = float(world.argv[world.argv.index("--epoch") + 1])
    recording = world.argv[world.argv.index("--recording-id") + 1]
    for agent, emulator in zip(agents, emulators, strict=True):
        spec = agent.spec
        assert spec is not None
        assert agent.argv == spawn_argv(spec, python=sys.executable)
        assert agent.argv[3:] == ["agent", "--robot", agent.name, "--fleet", "f", "--spec", "-"]
        assert (spec.robot_id, spec.fleet, spec.clock) == (agent.name, "f", "realtime")
        assert spec.overrides == ("duration_s=5",)
        assert spec.transport == TransportConfig(
            mode="client", connect=(ENDPOINT,), lowlatency=True
        )
        port = emulator.argv[emulator.argv.index("--tcp") + 1]
        assert spec.driver == DriverChoice(name="arcos", settings={"tcp": f"127.0.0.1:{port}"})
        assert spec.epoch_s == world_epoch  # one step 0 for every process
        assert spec.telemetry == TelemetryTarget(
            recording_id=recording, file=tmp_path / "telemetry" / f"{agent.name}.rrd"
        )


def test_the_factory_takes_the_scenario_with_its_overrides_and_robot() -> None:
    spec = AgentSpec(scenario=WEDGE, overrides=("duration_s=7",), robot_id="r3")
    scenario, robot = agent_scenario(spec)
    assert scenario.duration_s == 7.0
    assert robot.name == load_scenario(WEDGE).robot
    with pytest.raises(ConfigError, match="robot 'r9' is not in"):
        agent_scenario(spec.model_copy(update={"robot_id": "r9"}))
