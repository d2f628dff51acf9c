"""Deployment files, derived endpoints, command lines, and the host protocol's checks."""

from __future__ import annotations

import json
import threading
import time
import tomllib
from pathlib import Path

import pytest
from pydantic import ValidationError
from typer.testing import CliRunner

from phalanx.cli import app
from phalanx.core.config_files import CONFIG_ROOT, toml_value
from phalanx.core.errors import ConfigError
from phalanx.drivers.arcos import ArcosSettings
from phalanx.hosts.children import backoff_delay_s, exit_reason
from phalanx.hosts.daemon import HostDaemon
from phalanx.hosts.deployment import load_deployment
from phalanx.hosts.protocol import HostReply, SpawnRequest, line_level
from phalanx.hosts.wiring import (
    RunParameters,
    agent_spec,
    client_transport,
    host_connect,
    host_listen,
    host_transport,
    local_endpoint,
    recording_id,
    router_transport,
    world_argv,
)
from phalanx.runtime.process_spec import read_spec
from phalanx.runtime.signals import SignalStop

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
EXAMPLES = CONFIG_ROOT / "deployments"
HOSTS = """
[[hosts]]
name = "laptop"
address = "192.0.2.10"
[[hosts]]
name = "p3dx-1"
address = "192.0.2.11"
[[hosts]]
name = "p3dx-2"
address = "192.0.2.12"
"""
ROBOTS = """
[world]
host = "laptop"
[[robots]]
id = "r1"
host = "p3dx-1"
[[robots]]
id = "r2"
host = "p3dx-2"
[[robots]]
id = "r3"
host = "p3dx-2"
"""


def _write(tmp_path: Path, body: str, *, head: str = "", security: str = "open") -> Path:
    # The links' topology is the same in both modes; these tests read it over plain tcp/.
    text = f'name = "t"\nfleet = "t"\nscenario = "{WEDGE}"\n{head}\n{body}'
    text += f'\n[security]\nmode = "{security}"\n'
    path = tmp_path / "deployment.toml"
    path.write_text(text)
    return path


def _error(tmp_path: Path, body: str, *, head: str = "") -> str:
    with pytest.raises(ConfigError) as caught:
        load_deployment(_write(tmp_path, body, head=head))
    return str(caught.value)


@pytest.mark.parametrize("name", ["loopback", "lab_p3dx"])
def test_the_example_deployments_load(name: str) -> None:
    loaded = load_deployment(name)
    assert loaded.path == EXAMPLES / f"{name}.toml"
    assert {r.id for r in loaded.spec.robots} == {r.id for r in loaded.scenario.robots}
    assert len(loaded.digest) == 64


def test_the_real_robot_example_drives_p3dx_robots_over_serial() -> None:
    loaded = load_deployment("lab_p3dx")
    run = RunParameters("run1", epoch_unix=1.7e9)
    spec = agent_spec(loaded, "r2", run=run)
    assert spec.driver.name == "arcos"
    assert spec.driver.settings == ArcosSettings(port="/dev/ttyUSB0", baud=9600)
    assert spec.watchdog_s == 0.5
    assert spec.epoch_s == 1_700_000_000.0
    assert spec.transport.connect == ("tls/127.0.0.1:7447",)  # secured by default
    assert spec.transport.tls is not None
    assert spec.transport.tls.cert.endswith("/robot.r2.crt")
    assert spec.telemetry.recording_id == recording_id("lab", "run1")


def test_each_pair_of_hosts_shares_exactly_one_link(tmp_path: Path) -> None:
    spec = load_deployment(_write(tmp_path, HOSTS + ROBOTS)).spec
    assert host_connect(spec, "laptop") == ()
    assert host_connect(spec, "p3dx-1") == ("tcp/192.0.2.10:7447",)
    assert host_connect(spec, "p3dx-2") == ("tcp/192.0.2.10:7447", "tcp/192.0.2.11:7447")
    name_at = {f"tcp/{h.address}:7447": h.name for h in spec.hosts}
    links = [(h.name, name_at[e]) for h in spec.hosts for e in host_connect(spec, h.name)]
    assert len({frozenset(link) for link in links}) == len(links) == 3


def test_daemons_listen_on_their_ipv4_address_and_loopback_never_on_ipv6(tmp_path: Path) -> None:
    spec = load_deployment(_write(tmp_path, HOSTS + ROBOTS)).spec
    for host in spec.hosts:
        listen = host_listen(spec, host.name)
        assert listen == (f"tcp/{host.address}:7447", "tcp/127.0.0.1:7447")
        transport = host_transport(spec, host.name)
        assert transport.mode == "router"
        assert transport.multicast_scouting is False
        assert all("[" not in e for e in (*transport.listen, *transport.connect))
    assert local_endpoint(spec, "p3dx-1") == "tcp/127.0.0.1:7447"


def test_with_a_router_every_host_connects_to_it_alone(tmp_path: Path) -> None:
    head = '[zenoh]\nrouter = { address = "192.0.2.1" }\nmulticast = true\n'
    spec = load_deployment(_write(tmp_path, HOSTS + ROBOTS, head=head)).spec
    for host in spec.hosts:
        assert host_connect(spec, host.name) == ("tcp/192.0.2.1:7448",)
        assert not host_transport(spec, host.name).multicast_scouting  # the router decides
    router = router_transport(spec)
    assert router.listen == ("tcp/192.0.2.1:7448", "tcp/127.0.0.1:7448")
    assert client_transport(spec).connect == ("tcp/192.0.2.1:7448",)


def test_with_multicast_hosts_find_each_other_instead_of_connecting(tmp_path: Path) -> None:
    spec = load_deployment(_write(tmp_path, HOSTS + ROBOTS, head="[zenoh]\nmulticast = true")).spec
    for host in spec.hosts:
        transport = host_transport(spec, host.name)
        assert transport.connect == ()
        assert transport.multicast_scouting
        assert transport.autoconnect_routers
        assert transport.listen[0] == f"tcp/{host.address}:7447"


def test_a_launcher_joins_through_a_host_or_what_it_is_told(tmp_path: Path) -> None:
    spec = load_deployment(_write(tmp_path, HOSTS + ROBOTS)).spec
    assert client_transport(spec, via="p3dx-1").connect == ("tcp/127.0.0.1:7447",)
    assert client_transport(spec, connect=("tcp/192.0.2.99:1",)).connect == ("tcp/192.0.2.99:1",)
    everyone = client_transport(spec).connect  # no host is this machine: try them in order
    assert everyone == ("tcp/192.0.2.10:7447", "tcp/192.0.2.11:7447", "tcp/192.0.2.12:7447")
    loopback = load_deployment("loopback").spec
    assert client_transport(loopback).connect == ("tcp/127.0.0.1:7451",)


@pytest.mark.parametrize(
    ("body", "head", "expected"),
    [
        (HOSTS.replace("[[hosts]]", "[[hots]]", 1) + ROBOTS, "", "did you mean 'hosts'"),
        (HOSTS + ROBOTS.replace('host = "p3dx-1"', 'host = "p3dx1"'), "", "did you mean 'p3dx-1'"),
        (HOSTS + ROBOTS.replace('id = "r1"', 'id = "r11"'), "", "did you mean 'r1'"),
        (
            HOSTS + ROBOTS.replace('id = "r1"\nhost = "p3dx-1"\n', 'id = "r1"\nhots = "x"\n'),
            "",
            "did you mean 'host'",
        ),
        (HOSTS.replace("192.0.2.11", "fe80::1") + ROBOTS, "", "address"),
        (HOSTS.replace("192.0.2.11", "192.0.2.10") + ROBOTS, "", "endpoints must be unique"),
        (HOSTS.replace('"p3dx-2"', '"p3dx-1"', 1) + ROBOTS, "", "host names must be unique"),
        (HOSTS + ROBOTS.replace("[world]\nhost", "[world]\nhots"), "", "did you mean 'host'"),
        (
            HOSTS + ROBOTS,
            'clock = "lockstep"\noverrides = ["robots.0.driver=\\"arcos\\""]',
            "arcos",
        ),
    ],
)
def test_mistakes_are_named_with_a_hint(
    tmp_path: Path, body: str, head: str, expected: str
) -> None:
    assert expected in _error(tmp_path, body, head=head)


def test_robots_of_the_scenario_must_all_have_a_host(tmp_path: Path) -> None:
    body = HOSTS + ROBOTS.replace('[[robots]]\nid = "r3"\nhost = "p3dx-2"\n', "")
    assert "robots ['r3'] of the scenario have no host" in _error(tmp_path, body)


def _on_r1(lines: str) -> str:
    """ROBOTS with `lines` added to robot r1's placement."""
    return HOSTS + ROBOTS.replace('host = "p3dx-1"', f'host = "p3dx-1"\n{lines}')


def test_driver_settings_are_checked_by_the_backends_own_model(tmp_path: Path) -> None:
    arcos_without_link = _error(tmp_path, _on_r1('driver = "arcos"'))
    assert "deployment.toml: robot 'r1': arcos settings" in arcos_without_link
    assert "give exactly one of port (serial device) or tcp" in arcos_without_link
    both = _on_r1('driver = "arcos"\nsettings = { port = "/dev/ttyS0", tcp = "x:1" }')
    assert "give exactly one of port" in _error(tmp_path, both)
    misspelt = _error(
        tmp_path, _on_r1('driver = "arcos"\nsettings = { port = "/dev/x", bauds = 1 }')
    )
    assert "robot 'r1': arcos settings" in misspelt
    assert "bauds: Extra inputs are not permitted (did you mean 'baud'?)" in misspelt
    bad_value = _error(tmp_path, _on_r1('driver = "canopen"\nsettings = { bitrate = "fast" }'))
    assert "robot 'r1': canopen settings" in bad_value
    assert "bitrate: Input should be a valid integer" in bad_value
    geometry = _on_r1('driver = "canopen"\nsettings = { wheel_radius_m = 0.1 }')
    assert "wheel_radius_m: Extra inputs are not permitted" in _error(tmp_path, geometry)
    on_sim = _error(tmp_path, _on_r1('settings = { channel = "can1" }'))
    assert "robot 'r1': driver settings given but its driver is 'sim'" in on_sim
    old_syntax = _error(tmp_path, _on_r1('driver = "arcos"\narcos = { port = "/dev/ttyS0" }'))
    assert "arcos = {...} is now settings = {...}" in old_syntax
    lockstep = _on_r1('driver = "arcos"\nsettings = { tcp = "127.0.0.1:8101" }')
    assert "lockstep" in _error(tmp_path, lockstep, head='clock = "lockstep"')


def test_driver_settings_reach_the_agent_as_they_were(tmp_path: Path) -> None:
    settings = {
        "interface": "virtual",
        "channel": 'bus "7" \\ \t ü',
        "bitrate": 250000,
        "heartbeat_timeout_s": 0.25,
        "left_sign": -1,
    }
    table = ", ".join(f"{key} = {toml_value(value)}" for key, value in settings.items())
    path = _write(tmp_path, _on_r1(f'driver = "canopen"\nsettings = {{ {table} }}'))
    spec = agent_spec(load_deployment(path), "r1", run=RunParameters("run1"))
    (tmp_path / "r1.json").write_bytes(spec.encoded())  # as the agent reads it
    given = read_spec(tmp_path / "r1.json").driver
    assert given.name == "canopen"
    assert given.settings is not None
    assert given.settings.model_dump(include=set(settings)) == settings


@pytest.mark.parametrize(
    "value", [True, 0, -3, 1.5, 1e-9, float("inf"), "", 'a"b\\c\n\x7f\x00', [1, "x"], {"k": 2}]
)
def test_toml_values_read_back_as_they_were(value: object) -> None:
    assert tomllib.loads(f"v = {toml_value(value)}")["v"] == value


def test_the_world_command_line_comes_from_the_deployment(tmp_path: Path) -> None:
    loaded = load_deployment(_write(tmp_path, HOSTS + ROBOTS, head='overrides = ["seed=3"]'))
    run = RunParameters("run7", overrides=("duration_s=20",))
    argv = world_argv(loaded, run=run, out=tmp_path / "out" / "run7", python="python3")
    assert argv[:5] == ["python3", "-m", "phalanx", "world", str(WEDGE)]
    assert argv[argv.index("--connect") + 1] == "tcp/127.0.0.1:7447"
    assert argv[argv.index("--mode") + 1] == "client"
    assert argv[argv.index("--out") + 1] == str(tmp_path / "out" / "run7")
    assert [a for a in argv if a.startswith("--set=")] == ["--set=seed=3", "--set=duration_s=20"]
    assert "--epoch" not in argv  # simulated robots share the world's clock


def test_without_a_world_the_first_host_records_the_robots_on_drivers(tmp_path: Path) -> None:
    """A lab's deployment: no simulated world, every robot on its P3DX. The world process
    still runs (on the first host), simulating nobody: it records each robot from the
    best pose source it hears, and writes the results.
    """
    body = ROBOTS.replace('[world]\nhost = "laptop"\n', "").replace(
        'host = "p3dx-2"', 'host = "p3dx-2"\ndriver = "arcos"\nsettings = { tcp = "x:8101" }'
    )
    body = body.replace(
        'host = "p3dx-1"', 'host = "p3dx-1"\ndriver = "arcos"\nsettings = { port = "/dev/p3dx" }'
    )
    loaded = load_deployment(_write(tmp_path, HOSTS + body))
    assert loaded.spec.world is not None
    assert loaded.spec.world.host == "laptop"
    run = RunParameters("run8", epoch_unix=1_800_000_000.0)
    argv = world_argv(loaded, run=run, out=tmp_path / "out", python="python3")
    observed = [argv[i + 1] for i, a in enumerate(argv) if a == "--observe"]
    assert observed == ["r1", "r2", "r3"]
    assert argv[argv.index("--epoch") + 1] == "1800000000.000"


def test_spawn_requests_carry_no_commands() -> None:
    good = {"deployment": "lab", "digest": "a" * 64, "run_id": "r-1"}
    assert SpawnRequest.model_validate(good).robots == ()
    for bad in (
        {**good, "argv": ["sh", "-c", "x"]},
        {**good, "run_id": "a/b"},
        {**good, "overrides": ["x=1\n"]},
        {**good, "overrides": ["--driver=arcos"]},
        {**good, "robots": ["r 1"]},
        {**good, "epoch_unix": float("inf")},
        {**good, "digest": "xyz"},
    ):
        with pytest.raises(ValidationError):
            SpawnRequest.model_validate(bad)


def test_a_daemon_refuses_and_counts_bad_requests_without_starting_anything() -> None:
    loaded = load_deployment("loopback")
    daemon = HostDaemon(loaded, "robot-b")
    good = {"deployment": "loopback", "digest": loaded.digest, "run_id": "run1"}
    for payload in (
        b"junk",
        json.dumps({**good, "robots": ["r1"]}).encode(),
        json.dumps({**good, "digest": "b" * 64}).encode(),
        json.dumps({**good, "overrides": ["no_such_field=1"]}).encode(),
    ):
        reply = HostReply.model_validate_json(daemon.answer("spawn", payload))
        assert not reply.ok
        assert reply.error
    status = HostReply.model_validate_json(daemon.answer("status", b""))
    assert status.ok
    assert status.status.refused == 4
    assert status.status.requests == 5
    assert status.status.robots == ("r2", "r3")
    assert daemon.children == {}


def test_a_daemon_must_be_one_of_the_hosts() -> None:
    with pytest.raises(ConfigError, match="did you mean 'robot-a'"):
        HostDaemon(load_deployment("loopback"), "robot_a")


def test_restarts_back_off_exponentially_up_to_a_bound() -> None:
    policy = load_deployment("loopback").spec.restart
    delays = [backoff_delay_s(policy, step) for step in range(7)]
    assert delays == [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0]
    assert exit_reason(-9) == "killed by SIGKILL"
    assert exit_reason(2) == "exit 2"


def test_a_signal_stop_is_set_without_a_lock_and_wakes_a_waiter() -> None:
    stop = SignalStop()
    assert not stop.wait(0.05)
    timer = threading.Timer(0.1, stop.set)
    timer.start()
    started = time.monotonic()
    assert stop.wait(5.0)
    assert time.monotonic() - started < 1.0
    timer.join()
    stop.set()  # again: harmless
    assert stop.is_set()


def test_log_lines_are_graded() -> None:
    assert line_level("2026 r1 ERROR cannot reach the robot") == "error"
    assert line_level("Traceback (most recent call last):") == "error"
    assert line_level("2026 world WARNING robot r2 is gone") == "warning"
    assert line_level("r1: 100 steps") == "info"


def test_the_cli_names_a_broken_deployment_and_exits_2(tmp_path: Path) -> None:
    path = _write(tmp_path, HOSTS.replace("address", "adress", 1) + ROBOTS)
    for command in (["launch", str(path)], ["host", str(path)], ["status", str(path)]):
        result = CliRunner().invoke(app, command)
        assert result.exit_code == 2, result.output
        assert "did you mean 'address'" in result.output
    unknown = CliRunner().invoke(app, ["host", "loopback", "--name", "robot_a"])
    assert unknown.exit_code == 2
    assert "did you mean 'robot-a'" in unknown.output
