"""Deployment files: which robot runs on which host, and how the hosts reach each other.

A deployment file (`configs/deployments/*.toml`) names a fleet and its scenario, the hosts
(one `phalanx host` daemon each) with their addresses, every robot with its host, driver
and driver settings, where the world runs (if anywhere), and a few Zenoh settings.
Nothing else is configured by hand: every endpoint is derived here.

- Each host's daemon is a Zenoh router listening on `tcp/<address>:<port>` (IPv4; never
  `[::]`, so hosts without IPv6 work) and on `tcp/127.0.0.1:<port>` for its children.
- Hosts are joined by exactly one TCP link per pair: each host connects to the hosts
  listed before it. (When both ends of a pair connect, Zenoh makes one transport of two
  links, and after a lost link that transport can stay half-open until the network comes
  back: measured, see docs/DEPLOYMENT.md.) Lost links are retried every `retry_max_ms`.
- With `[zenoh.router]`, every host connects to that router only (`phalanx router`), for
  networks where hosts cannot reach each other.
- With `multicast = true` (and no router), hosts find each other by multicast scouting
  instead, one link per pair (the router with the greater Zenoh id connects). Slower to
  rejoin after a loss (scouting's period), and the network must carry multicast.
- Agents and the world are Zenoh clients of their own host's daemon on 127.0.0.1.
"""

from __future__ import annotations

import difflib
import hashlib
import ipaddress
import socket
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from phalanx.core.config import DriverKind, Scenario, apply_overrides, load_scenario, validate_file
from phalanx.core.errors import ConfigError
from phalanx.wire.transport import TransportConfig

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


class HostEntry(Model):
    """A machine of the fleet: it runs `phalanx host DEPLOYMENT --name NAME`."""

    name: Name
    address: str = Field(pattern=_ADDRESS)  # IPv4 address (or a name resolving to one)
    port: Port | None = None  # default: zenoh.port
    bind: str | None = None  # IPv4 address to listen on (default: address, if IPv4)

    @model_validator(mode="after")
    def _bind_is_ipv4(self) -> Self:
        _ipv4(self.bind, "bind")
        return self


class ArcosEntry(Model):
    """A P3DX on ARCOS: its serial device, or host:port of a serial-to-TCP bridge."""

    port: str | None = None
    tcp: str | None = None
    baud: int = Field(default=9600, gt=0)

    @model_validator(mode="after")
    def _one_link(self) -> Self:
        if (self.port is None) == (self.tcp is None):
            raise ValueError("give exactly one of arcos.port (serial device) and arcos.tcp")
        return self


class CanopenEntry(Model):
    """Two CiA 402 drives on a CAN bus (python-can interface and channel)."""

    interface: str = Field(default="socketcan", pattern=r"^[A-Za-z0-9_-]{1,32}$")
    channel: str = Field(default="can0", pattern=r"^[A-Za-z0-9_./:-]{1,64}$")


class RobotPlacement(Model):
    """Where a robot's agent runs and what drives it (default: the scenario's driver)."""

    id: Name
    host: Name
    driver: DriverKind | None = None
    arcos: ArcosEntry | None = None
    canopen: CanopenEntry | None = None
    watchdog_s: float = Field(default=0.5, gt=0.0, le=2.0)  # under ARCOS's own 2 s


class WorldPlacement(Model):
    """The simulated world's host, and where it writes results (on that host)."""

    host: Name
    speed: float = Field(default=1.0, gt=0.0, le=1000.0)
    out_dir: str = "results/deployments"  # relative: to the daemon's working directory
    recording: bool = True


class RestartPolicy(Model):
    """How a host daemon restarts a crashed agent: exponential back-off, bounded."""

    max_restarts: int = Field(default=5, ge=0, le=1000)
    backoff_s: float = Field(default=0.5, gt=0.0)
    backoff_max_s: float = Field(default=10.0, gt=0.0)
    stable_s: float = Field(default=30.0, gt=0.0)  # running this long resets the back-off


class TelemetrySettings(Model):
    """Stream every process's telemetry to a Rerun viewer (`phalanx view --bind 0.0.0.0`)."""

    url: str | None = Field(default=None, pattern=r"^rerun(\+https?)?://[^\s]{1,200}$")


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
    max_clock_skew_s: float = Field(default=0.05, gt=0.0)
    zenoh: ZenohSettings = ZenohSettings()
    hosts: tuple[HostEntry, ...] = Field(min_length=1)
    robots: tuple[RobotPlacement, ...] = Field(min_length=1)
    world: WorldPlacement | None = None
    restart: RestartPolicy = RestartPolicy()
    telemetry: TelemetrySettings = TelemetrySettings()

    @model_validator(mode="after")
    def _references(self) -> Self:
        names = [h.name for h in self.hosts]
        _unique(names, "host names")
        _unique([r.id for r in self.robots], "robot ids")
        _unique([(_bind(h) or h.address, self.port_of(h.name)) for h in self.hosts], "endpoints")
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
        return self

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


def _bind(host: HostEntry) -> str | None:
    if host.bind is not None:
        return host.bind
    try:
        return str(ipaddress.IPv4Address(host.address))
    except ValueError:
        return None


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
        scenario = apply_overrides(scenario, list(spec.overrides))
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
    if driver == "arcos" and robot.arcos is None:
        raise ConfigError(f"{where}: robot {robot.id!r} uses arcos: give arcos.port or arcos.tcp")
    for kind, given in (("arcos", robot.arcos), ("canopen", robot.canopen)):
        if given is not None and driver != kind:
            raise ConfigError(
                f"{where}: robot {robot.id!r}: {kind} settings given but its driver is {driver!r}"
            )


# --- endpoints --------------------------------------------------------------------------


def endpoint(address: str, port: int) -> str:
    """`tcp/<address>:<port>`."""
    return f"tcp/{address}:{port}"


def host_endpoint(spec: Deployment, name: str) -> str:
    """Where other machines reach host `name`'s daemon."""
    return endpoint(spec.host(name).address, spec.port_of(name))


def local_endpoint(spec: Deployment, name: str) -> str:
    """Where processes on host `name` reach its daemon: loopback."""
    return endpoint("127.0.0.1", spec.port_of(name))


def host_listen(spec: Deployment, name: str) -> tuple[str, ...]:
    """The daemon's listen endpoints: its IPv4 address and loopback."""
    host, port = spec.host(name), spec.port_of(name)
    bind = _bind(host) or "0.0.0.0"  # noqa: S104 - a name we cannot pin: every interface
    if bind == "0.0.0.0" or ipaddress.IPv4Address(bind).is_loopback:  # noqa: S104
        return (endpoint(bind, port),)
    return (endpoint(bind, port), endpoint("127.0.0.1", port))


def host_connect(spec: Deployment, name: str) -> tuple[str, ...]:
    """The daemon's connect endpoints: the router, or every host listed before it.

    With multicast and no router: none, the hosts find each other (explicit links as well
    would make two links of some pairs: see the module's docstring).
    """
    spec.host(name)  # raises the "no such host" error
    router = spec.zenoh.router
    if router is not None:
        return (endpoint(router.address, router.port),)
    if spec.zenoh.multicast:
        return ()
    before: list[str] = []
    for host in spec.hosts:
        if host.name == name:
            return tuple(before)
        before.append(host_endpoint(spec, host.name))
    return ()


def _fabric(spec: Deployment, **values: object) -> TransportConfig:
    zenoh = spec.zenoh
    discover = zenoh.multicast and zenoh.router is None
    return TransportConfig.model_validate(
        {
            "multicast_scouting": discover,
            "autoconnect_routers": discover,
            "lease_ms": zenoh.lease_ms,
            "keep_alive": zenoh.keep_alive,
            "retry_max_ms": zenoh.retry_max_ms,
            **values,
        }
    )


def host_transport(spec: Deployment, name: str) -> TransportConfig:
    """The Zenoh configuration of host `name`'s daemon (a router)."""
    return _fabric(
        spec, mode="router", listen=host_listen(spec, name), connect=host_connect(spec, name)
    )


def router_transport(spec: Deployment) -> TransportConfig:
    """The Zenoh configuration of `phalanx router` for this deployment."""
    router = spec.zenoh.router
    if router is None:
        raise ConfigError(f"deployment {spec.name!r} has no [zenoh.router]")
    bind = router.bind or str(_router_bind(router))
    listen = [endpoint(bind, router.port)]
    if bind != "0.0.0.0" and not ipaddress.IPv4Address(bind).is_loopback:  # noqa: S104
        listen.append(endpoint("127.0.0.1", router.port))
    return _fabric(spec, mode="router", listen=tuple(listen), connect=())


def _router_bind(router: RouterEntry) -> str:
    try:
        return str(ipaddress.IPv4Address(router.address))
    except ValueError:
        return "0.0.0.0"  # noqa: S104 - a name we cannot pin: every interface


def client_transport(
    spec: Deployment, *, via: str | None = None, connect: tuple[str, ...] = ()
) -> TransportConfig:
    """How a launcher (or `status`, `stop`) joins: a client of one router.

    `connect` wins; then host `via`'s daemon; then the local daemon if this machine is one
    of the hosts; then the router; then every host in order (the first one reachable).
    """
    if not connect:
        local = via or next(iter(local_hosts(spec)), None)
        if local is not None:
            connect = (local_endpoint(spec, local),)
        elif spec.zenoh.router is not None:
            connect = (endpoint(spec.zenoh.router.address, spec.zenoh.router.port),)
        else:
            connect = tuple(host_endpoint(spec, h.name) for h in spec.hosts)
    return _fabric(spec, mode="client", connect=connect, open_timeout_s=5.0)


def is_local_address(address: str) -> bool:
    """Whether `address` (IPv4 literal) belongs to this machine: binding to it works."""
    try:
        ipaddress.IPv4Address(address)
    except ValueError:
        return address in ("localhost", socket.gethostname())
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((address, 0))
        except OSError:
            return False
    return True


def local_hosts(spec: Deployment) -> tuple[str, ...]:
    """The hosts whose address is on this machine (loopback hosts first)."""
    here = [h for h in spec.hosts if is_local_address(h.address)]
    here.sort(key=lambda h: not h.address.startswith("127."))
    return tuple(h.name for h in here)


def loopback_hosts(spec: Deployment) -> tuple[str, ...]:
    """The hosts on a loopback address (a fleet on one machine: `launch --local`)."""
    return tuple(h.name for h in spec.hosts if h.address.startswith("127."))


# --- command lines ----------------------------------------------------------------------


@dataclass(frozen=True)
class RunParameters:
    """What a launcher chooses for one run; validated before it reaches a command line."""

    run_id: str
    epoch_unix: float | None = None
    overrides: tuple[str, ...] = ()


def recording_id(fleet: str, run_id: str) -> str:
    """The Rerun recording id shared by every process of a run."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"phalanx/{fleet}/{run_id}"))


def _common(loaded: LoadedDeployment, host: str, run: RunParameters) -> list[str]:
    spec = loaded.spec
    argv = ["--fleet", spec.fleet, "--clock", spec.clock, "--mode", "client"]
    argv += ["--connect", local_endpoint(spec, host)]
    argv += [f"--set={o}" for o in (*spec.overrides, *run.overrides)]
    if spec.telemetry.url is not None:
        argv += ["--recording-id", recording_id(spec.fleet, run.run_id)]
        argv += ["--telemetry-url", spec.telemetry.url]
    return argv


def agent_argv(
    loaded: LoadedDeployment, robot_id: str, *, run: RunParameters, python: str
) -> list[str]:
    """The command line of a robot's agent, built from the deployment alone."""
    placement = loaded.spec.placement(robot_id)
    argv = [python, "-m", "phalanx", "agent", str(loaded.scenario_path), "--robot", robot_id]
    argv += _common(loaded, placement.host, run)
    return argv + _driver_args(loaded, placement, run)


def _driver_args(
    loaded: LoadedDeployment, placement: RobotPlacement, run: RunParameters
) -> list[str]:
    driver = loaded.driver_of(placement.id)
    argv = ["--driver", driver]
    if driver == "sim":
        return argv
    argv += ["--watchdog", repr(placement.watchdog_s)]
    if run.epoch_unix is not None:
        argv += ["--epoch", f"{run.epoch_unix:.3f}"]
    if driver == "arcos" and placement.arcos is not None:
        arcos = placement.arcos
        link = ["--arcos-port", arcos.port] if arcos.port else ["--arcos-tcp", str(arcos.tcp)]
        return argv + link + ["--baud", str(arcos.baud)]
    canopen = placement.canopen or CanopenEntry()
    return [*argv, "--can-interface", canopen.interface, "--can-channel", canopen.channel]


def world_argv(
    loaded: LoadedDeployment, *, run: RunParameters, out: Path, python: str
) -> list[str]:
    """The command line of the world, built from the deployment alone."""
    spec, world = loaded.spec, loaded.spec.world
    if world is None:
        raise ConfigError(f"deployment {spec.name!r} has no [world]")
    argv = [python, "-m", "phalanx", "world", str(loaded.scenario_path)]
    argv += _common(loaded, world.host, run)
    argv += ["--speed", repr(world.speed), "--out", str(out)]
    argv.append("--recording" if world.recording else "--no-recording")
    if spec.clock == "realtime" and run.epoch_unix is not None:
        argv += ["--epoch", f"{run.epoch_unix:.3f}"]
    return argv


def needs_epoch(loaded: LoadedDeployment) -> bool:
    """Whether a run needs a shared epoch: some robot keeps its own clock (a real driver)."""
    return any(loaded.driver_of(r.id) != "sim" for r in loaded.spec.robots)
