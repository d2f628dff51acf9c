"""Deployment files: which robot runs on which host, and how the hosts reach each other.

A deployment file (`configs/deployments/*.toml`) names a fleet and its scenario, the hosts
(one `phalanx host` daemon each) with their addresses, every robot with its host, driver
and driver settings, where the world runs (if anywhere), and a few Zenoh settings. This
module reads and checks it: every key (unknown ones refused with the closest valid name),
the references between hosts, robots and the world, the file against its scenario, and
each robot's driver settings against its driver backend's own settings model
(`phalanx.drivers.validate_settings`). Everything else, endpoints and command lines, is
derived from it in `phalanx.hosts.wiring`.
"""

from __future__ import annotations

import difflib
import hashlib
import ipaddress
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from phalanx.core.config import DriverKind, Ros2Config, Scenario
from phalanx.core.config_files import apply_overrides, load_scenario, validate_file
from phalanx.core.errors import ConfigError
from phalanx.core.quantities import PositiveDuration
from phalanx.drivers import validate_settings

NAME_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
DEPLOYMENTS_DIR = Path(__file__).resolve().parents[2] / "configs" / "deployments"
Name = Annotated[str, Field(pattern=NAME_PATTERN)]
Port = Annotated[int, Field(ge=1, le=65535)]
_ADDRESS = r"^[A-Za-z0-9][A-Za-z0-9.-]{0,252}$"


class Model(BaseModel):
    """Base of the deployment models: unknown keys rejected, values frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def _ipv4(value: str | None, what: str) -> str | None:
    if value is not None:
        try:
            ipaddress.IPv4Address(value)
        except ValueError as exc:
            raise ValueError(f"{what} {value!r}: expected an IPv4 address") from exc
    return value


def did_you_mean(value: str, choices: Iterable[str]) -> str:
    """` (did you mean 'x'?)` for the closest of `choices`, or an empty string."""
    hints = difflib.get_close_matches(value, list(choices), n=1)
    return f" (did you mean {hints[0]!r}?)" if hints else ""


class RouterEntry(Model):
    """A `phalanx router` every host connects to, instead of to each other."""

    address: str = Field(pattern=_ADDRESS)
    port: Port = 7448  # beside the daemons' 7447, should the router share a machine
    bind: str | None = None  # IPv4 address the router listens on (default: `address`)

    @model_validator(mode="after")
    def _bind_is_ipv4(self) -> Self:
        _ipv4(self.bind, "bind")
        return self


class ZenohSettings(Model):
    """How the hosts' daemons join the fabric."""

    port: Port = 7447  # every host's daemon port unless the host gives its own
    lease_ms: int = Field(default=1000, ge=100, le=60_000)  # a lost link is noticed after this
    keep_alive: int = Field(default=4, ge=1, le=16)  # keep-alives per lease
    retry_max_ms: int = Field(default=1000, ge=100, le=60_000)  # reconnect period, at most
    multicast: bool = False  # also find the other hosts by multicast scouting
    router: RouterEntry | None = None


class SecuritySettings(Model):
    """How the fleet's links are secured (docs/SECURITY.md).

    `mode = "mtls"`: every link is `tls/` with mutual authentication against the fleet's
    CA, and each host's router applies the access-control list generated from this file;
    `mode = "open"`: plain TCP, anyone who reaches a port can drive the robots (warned
    about at every start). Without a `[security]` table a deployment is `mtls`, except one
    whose hosts are all on loopback addresses (one machine), which is `open` quietly.
    """

    mode: Literal["mtls", "open"] = "mtls"
    pki: str = "pki"  # folder of `ca.crt` and `<common name>.crt/.key`, relative to the file
    ca: str | None = None  # the CA's certificate (default: <pki>/ca.crt)
    operators: tuple[Name, ...] = ()  # who may start and stop the fleet (operator.NAME)
    viewers: tuple[Name, ...] = ()  # who may read it (viewer.NAME)
    may_override: tuple[Name, ...] = ()  # operators whose `--set` is accepted (allow_overrides)
    request_window_s: float = Field(default=30.0, gt=0.0, le=600.0)  # a request's age, at most


class HostEntry(Model):
    """A machine of the fleet: it runs `phalanx host DEPLOYMENT --name NAME`."""

    name: Name
    address: str = Field(pattern=_ADDRESS)  # IPv4 address (or a name resolving to one)
    port: Port | None = None  # default: zenoh.port
    bind: str | None = None  # IPv4 address to listen on (default: address, if IPv4)
    cert: str | None = None  # its certificate (default: <pki>/host.<name>.crt)
    key: str | None = None  # its key (default: <pki>/host.<name>.key)

    @model_validator(mode="after")
    def _bind_is_ipv4(self) -> Self:
        _ipv4(self.bind, "bind")
        return self

    def bind_address(self) -> str | None:
        """The IPv4 address to listen on: `bind`, else `address` if it is one, else None."""
        if self.bind is not None:
            return self.bind
        try:
            return str(ipaddress.IPv4Address(self.address))
        except ValueError:
            return None


class RobotPlacement(Model):
    """Where a robot's agent runs and what drives it (default: the scenario's driver).

    `settings` is a table of the driver backend's own settings, e.g. for arcos
    `{ port = "/dev/ttyUSB0", baud = 9600 }`, checked by that backend's model on loading.
    """

    id: Name
    host: Name
    driver: DriverKind | None = None
    settings: dict[str, Any] = Field(default_factory=dict)
    watchdog_s: float = Field(default=0.5, gt=0.0, le=2.0)  # under ARCOS's own 2 s

    @model_validator(mode="before")
    @classmethod
    def _no_backend_tables(cls, data: Any) -> Any:
        for old in ("arcos", "canopen"):
            if isinstance(data, dict) and old in data:
                raise ValueError(f"{old} = {{...}} is now settings = {{...}}")
        return data


class WorldPlacement(Model):
    """The world process's host, and where it writes results (on that host). The world
    simulates the robots on the sim driver and records every robot (those on real
    drivers from their best pose source); a deployment without `[world]` runs it on its
    first host.
    """

    host: Name
    speed: float = Field(default=1.0, gt=0.0, le=1000.0)
    out_dir: str = "results/deployments"  # relative: to the daemon's working directory
    recording: bool = True


class RestartPolicy(Model):
    """How a host daemon restarts a crashed agent: exponential back-off, bounded."""

    max_restarts: int = Field(default=5, ge=0, le=1000)
    backoff_s: PositiveDuration = 0.5
    backoff_max_s: PositiveDuration = 10.0
    stable_s: PositiveDuration = 30.0  # running this long resets the back-off


class TelemetrySettings(Model):
    """Stream every process's telemetry to a Rerun viewer (`phalanx view --bind 0.0.0.0`)."""

    url: str | None = Field(default=None, pattern=r"^rerun(\+https?)?://[^\s]{1,200}$")


class Ros2Bridge(Ros2Config):
    """`[ros2]` of a deployment: the fleet seen from ROS 2 (docs/ROS2.md), the fields of
    a scenario's `[ros2]` (they stand for the scenario's), and where the bridge runs: it
    joins `host`'s daemon (default: the world's host) with the certificate
    `viewer.<identity>`, whose access rules, when `enabled`, let it publish exactly the
    bridge's ROS keys.
    """

    host: Name | None = None
    identity: Name = "ros2"


class Deployment(Model):
    """A fleet on one or many hosts: the contents of a deployment file."""

    name: Name
    description: str = ""
    fleet: Name
    scenario: str  # path, relative to the deployment file
    overrides: tuple[str, ...] = ()  # scenario overrides, as `--set PATH=VALUE`
    clock: Literal["realtime", "lockstep"] = "realtime"
    startup_s: float = Field(default=10.0, ge=0.0, le=600.0)  # robot drivers: epoch offset
    allow_overrides: bool = True  # accept `phalanx launch --set ...` from the network
    max_clock_skew_s: float = Field(default=0.05, gt=0.0, le=60.0)
    zenoh: ZenohSettings = ZenohSettings()
    hosts: tuple[HostEntry, ...] = Field(min_length=1)
    robots: tuple[RobotPlacement, ...] = Field(min_length=1)
    world: WorldPlacement | None = None
    restart: RestartPolicy = RestartPolicy()
    telemetry: TelemetrySettings = TelemetrySettings()
    security: SecuritySettings | None = None
    ros2: Ros2Bridge | None = None

    @model_validator(mode="before")
    @classmethod
    def _world_somewhere(cls, data: Any) -> Any:
        """No `[world]`: the world (the run's record, at least) runs on the first host."""
        if not isinstance(data, dict) or data.get("world") is not None:
            return data
        hosts = data.get("hosts")
        first = hosts[0] if isinstance(hosts, list | tuple) and hosts else None
        if isinstance(first, dict) and isinstance(first.get("name"), str):
            return {**data, "world": {"host": first["name"]}}
        return data

    @model_validator(mode="after")
    def _references(self) -> Self:
        names = [h.name for h in self.hosts]
        _unique(names, "host names")
        _unique([r.id for r in self.robots], "robot ids")
        _unique(
            [(h.bind_address() or h.address, self.port_of(h.name)) for h in self.hosts], "endpoints"
        )
        for robot in self.robots:
            if robot.host not in names:
                raise ValueError(
                    f"robot {robot.id!r}: host {robot.host!r} is not in hosts"
                    + did_you_mean(robot.host, names)
                )
        if self.world is not None and self.world.host not in names:
            raise ValueError(
                f"world: host {self.world.host!r} is not in hosts"
                + did_you_mean(self.world.host, names)
            )
        bridge_host = self.ros2.host if self.ros2 is not None else None
        if bridge_host is not None and bridge_host not in names:
            raise ValueError(
                f"ros2: host {bridge_host!r} is not in hosts" + did_you_mean(bridge_host, names)
            )
        if self.security is not None:
            for name in self.security.may_override:
                if name not in self.security.operators:
                    raise ValueError(f"security.may_override: {name!r} is not in operators")
        return self

    @property
    def secured(self) -> bool:
        """Whether links are mutual TLS with access control (see `SecuritySettings`)."""
        if self.security is not None:
            return self.security.mode == "mtls"
        return not self.on_loopback

    @property
    def on_loopback(self) -> bool:
        """Whether every host is on a loopback address (the fleet is on one machine)."""
        return all(h.address.startswith("127.") or h.address == "localhost" for h in self.hosts)

    @property
    def open_warning(self) -> str | None:
        """The warning an explicitly open deployment prints at every start, if it is one."""
        if self.security is None or self.security.mode != "open":
            return None
        return (
            f"WARNING: deployment {self.name!r} runs with security mode = 'open': no "
            "encryption, no authentication, no access control. Anyone who can reach its "
            "ports can read the fleet, drive its robots and start or stop it. Use "
            "mode = 'mtls' (docs/SECURITY.md)"
        )

    def host(self, name: str) -> HostEntry:
        """The host called `name` (ConfigError naming the closest one otherwise)."""
        for entry in self.hosts:
            if entry.name == name:
                return entry
        names = [h.name for h in self.hosts]
        raise ConfigError(
            f"deployment {self.name!r} has no host {name!r}{did_you_mean(name, names)}; "
            f"hosts: {', '.join(names)}"
        )

    def port_of(self, name: str) -> int:
        """The daemon port of host `name`."""
        return self.host(name).port or self.zenoh.port

    def robots_on(self, name: str) -> tuple[str, ...]:
        """Ids of the robots whose agents run on host `name`, in file order."""
        return tuple(r.id for r in self.robots if r.host == name)

    def placement(self, robot_id: str) -> RobotPlacement:
        """The placement of robot `robot_id`."""
        return next(r for r in self.robots if r.id == robot_id)

    def runs_world(self, name: str) -> bool:
        """Whether host `name` runs the world."""
        return self.world is not None and self.world.host == name


def _unique(values: Sequence[object], what: str) -> None:
    seen: set[object] = set()
    for value in values:
        if value in seen:
            raise ValueError(f"{what} must be unique: {value!r} appears twice")
        seen.add(value)


# --- loading ----------------------------------------------------------------------------


@dataclass(frozen=True)
class LoadedDeployment:
    """A validated deployment with its scenario (deployment overrides applied)."""

    path: Path
    spec: Deployment
    scenario_path: Path
    scenario: Scenario
    digest: str  # sha256 of the deployment file and the scenario file

    def driver_of(self, robot_id: str) -> DriverKind:
        """The robot's driver: the deployment's, else the scenario's."""
        placed = self.spec.placement(robot_id).driver
        if placed is not None:
            return placed
        return next(r.driver for r in self.scenario.robots if r.id == robot_id)


def resolve_deployment_path(name_or_path: str | Path) -> Path:
    """A deployment path, or the name of a file in configs/deployments."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        return path
    return DEPLOYMENTS_DIR / f"{name_or_path}.toml"


def load_deployment(name_or_path: str | Path) -> LoadedDeployment:
    """Load and cross-check a deployment file and its scenario; ConfigError on any fault."""
    path = resolve_deployment_path(name_or_path)
    spec = validate_file(Deployment, path)
    scenario_path = (path.parent / spec.scenario).resolve()
    if not scenario_path.is_file():
        raise ConfigError(f"{path}: scenario {spec.scenario!r}: no such file ({scenario_path})")
    scenario = load_scenario(scenario_path)
    if spec.overrides:
        scenario = apply_overrides(scenario, list(spec.overrides), source=f"{path}: overrides")
    digest = hashlib.sha256(path.read_bytes() + b"\0" + scenario_path.read_bytes()).hexdigest()
    loaded = LoadedDeployment(path, spec, scenario_path, scenario, digest)
    _check_against_scenario(loaded)
    return loaded


def _check_against_scenario(loaded: LoadedDeployment) -> None:
    spec, where = loaded.spec, loaded.path
    wanted = [r.id for r in loaded.scenario.robots]
    placed = [r.id for r in spec.robots]
    for rid in placed:
        if rid not in wanted:
            raise ConfigError(
                f"{where}: robot {rid!r} is not in scenario {loaded.scenario.name!r}"
                + did_you_mean(rid, wanted)
            )
    missing = [rid for rid in wanted if rid not in placed]
    if missing:
        raise ConfigError(f"{where}: robots {missing} of the scenario have no host")
    for robot in spec.robots:
        _check_driver_settings(where, robot, loaded.driver_of(robot.id))
    real = [rid for rid in placed if loaded.driver_of(rid) != "sim"]
    if spec.clock == "lockstep" and (spec.world is None or real):
        raise ConfigError(
            f"{where}: clock = 'lockstep' needs a [world] and only sim robots "
            f"(robots on real drivers: {real}); use clock = 'realtime'"
        )
    sims = [rid for rid in placed if loaded.driver_of(rid) == "sim"]
    if sims and spec.world is None:
        raise ConfigError(f"{where}: robots {sims} use the sim driver but there is no [world]")


def _check_driver_settings(where: Path, robot: RobotPlacement, driver: DriverKind) -> None:
    """The robot's `settings`, checked by its driver backend's own settings model."""
    if driver == "sim":
        if robot.settings:
            raise ConfigError(
                f"{where}: robot {robot.id!r}: driver settings given but its driver is 'sim' "
                "(the world moves it)"
            )
        return
    validate_settings(
        driver, robot.settings, source=f"{where}: robot {robot.id!r}: {driver} settings"
    )


def needs_epoch(loaded: LoadedDeployment) -> bool:
    """Whether a run needs a shared epoch: some robot keeps its own clock (a real driver)."""
    return any(loaded.driver_of(r.id) != "sim" for r in loaded.spec.robots)
