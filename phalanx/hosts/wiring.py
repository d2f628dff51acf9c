"""What a deployment implies: every process's Zenoh endpoints and transport, and what the
host daemons run (each agent's spec, the world's command line). Nothing here is
configured by hand.

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
- A robot's driver and its settings reach its agent in its spec (`agent_spec`), checked
  by the driver backend's own settings model when the spec is built and again when the
  agent reads it.
- A secured deployment (`[security] mode = "mtls"`, see `Deployment.secured`) uses `tls/`
  endpoints everywhere, loopback included: every process presents its own certificate
  (`robot.<id>`, `world`, `host.<name>`, `operator.<name>`, the ROS 2 bridge's
  `viewer.<identity>`), and each daemon's router applies the access-control list of
  `phalanx.hosts.access`.
- With `[ros2] enabled`, the bridge's host (`ros2.host`, else the world's) runs `phalanx
  ros2 --deployment`: a client of its daemon, meeting ROS 2 at `[ros2] connect` (else
  rmw_zenoh's default router) on a session of its own.
"""

from __future__ import annotations

import ipaddress
import socket
import uuid
from dataclasses import dataclass
from pathlib import Path

from phalanx.core.config import ROS_ROUTER
from phalanx.core.errors import ConfigError
from phalanx.hosts.access import bridge_host, host_acl, host_files, identity_files
from phalanx.hosts.deployment import Deployment, LoadedDeployment, RouterEntry
from phalanx.hosts.pki import common_name
from phalanx.runtime.process_spec import AgentSpec, DriverChoice, TelemetryTarget
from phalanx.wire.security import TlsFiles
from phalanx.wire.transport import TransportConfig

# --- endpoints --------------------------------------------------------------------------


def endpoint(address: str, port: int, scheme: str = "tcp") -> str:
    """`<scheme>/<address>:<port>` (`tcp`, or `tls` for a secured deployment)."""
    return f"{scheme}/{address}:{port}"


def scheme(spec: Deployment) -> str:
    """`tls` for a secured deployment, else `tcp`."""
    return "tls" if spec.secured else "tcp"


def host_endpoint(spec: Deployment, name: str) -> str:
    """Where other machines reach host `name`'s daemon."""
    return endpoint(spec.host(name).address, spec.port_of(name), scheme(spec))


def local_endpoint(spec: Deployment, name: str) -> str:
    """Where processes on host `name` reach its daemon: loopback."""
    return endpoint("127.0.0.1", spec.port_of(name), scheme(spec))


def host_listen(spec: Deployment, name: str) -> tuple[str, ...]:
    """The daemon's listen endpoints: its IPv4 address and loopback."""
    host, port, kind = spec.host(name), spec.port_of(name), scheme(spec)
    bind = host.bind_address() or "0.0.0.0"  # noqa: S104 - a name we cannot pin: every interface
    if bind == "0.0.0.0" or ipaddress.IPv4Address(bind).is_loopback:  # noqa: S104
        return (endpoint(bind, port, kind),)
    return (endpoint(bind, port, kind), endpoint("127.0.0.1", port, kind))


def host_connect(spec: Deployment, name: str) -> tuple[str, ...]:
    """The daemon's connect endpoints: the router, or every host listed before it.

    With multicast and no router: none, the hosts find each other (explicit links as well
    would make two links of some pairs: see the module's docstring).
    """
    spec.host(name)  # raises the "no such host" error
    router = spec.zenoh.router
    if router is not None:
        return (endpoint(router.address, router.port, scheme(spec)),)
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
    """The Zenoh configuration of host `name`'s daemon (a router), without its files."""
    return _fabric(
        spec, mode="router", listen=host_listen(spec, name), connect=host_connect(spec, name)
    )


def secured_host_transport(loaded: LoadedDeployment, name: str) -> TransportConfig:
    """Host `name`'s daemon's configuration with, when secured, its TLS files and its
    access-control list (ConfigError naming a missing file and how to issue it).
    """
    transport = host_transport(loaded.spec, name)
    if not loaded.spec.secured:
        return transport
    update = {"tls": host_files(loaded, name), "acl": host_acl(loaded.spec, name)}
    children = [common_name("robot", r) for r in loaded.spec.robots_on(name)]
    children += ["world"] if loaded.spec.runs_world(name) else []
    ros2 = loaded.spec.ros2
    if ros2 is not None and bridge_host(loaded.spec) == name:
        children.append(common_name("viewer", ros2.identity))
    for identity in children:
        identity_files(loaded, identity)  # every child's files are here, or say which is not
    return transport.model_copy(update=update)


def client_identity(loaded: LoadedDeployment, identity: str | None) -> TlsFiles | None:
    """The TLS files a launcher, `status` or `stop` presents (None: not secured).

    `identity` is a common name in the PKI folder or a path without suffix; by default
    `$PHALANX_IDENTITY`, else the deployment's only operator.
    """
    if not loaded.spec.secured:
        return None
    import os

    chosen = identity or os.environ.get("PHALANX_IDENTITY")
    operators = loaded.spec.security.operators if loaded.spec.security else ()
    if chosen is None and len(operators) == 1:
        chosen = common_name("operator", operators[0])
    if chosen is None:
        raise ConfigError(
            f"{loaded.path}: a secured deployment needs an identity: --identity "
            "operator.NAME (or viewer.NAME), or PHALANX_IDENTITY"
        )
    return identity_files(loaded, chosen)


def router_transport(spec: Deployment) -> TransportConfig:
    """The Zenoh configuration of `phalanx router` for this deployment."""
    router = spec.zenoh.router
    if router is None:
        raise ConfigError(f"deployment {spec.name!r} has no [zenoh.router]")
    if spec.secured:
        raise ConfigError(
            f"deployment {spec.name!r}: `phalanx router` does not run under security mode "
            "'mtls' yet: join the hosts directly, or use mode = 'open' on a closed network"
        )
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
    spec: Deployment,
    *,
    via: str | None = None,
    connect: tuple[str, ...] = (),
    tls: TlsFiles | None = None,
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
            router = spec.zenoh.router
            connect = (endpoint(router.address, router.port, scheme(spec)),)
        else:
            connect = tuple(host_endpoint(spec, h.name) for h in spec.hosts)
    return _fabric(spec, mode="client", connect=connect, open_timeout_s=5.0, tls=tls)


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


# --- what the daemons run ---------------------------------------------------------------


@dataclass(frozen=True)
class RunParameters:
    """What a launcher chooses for one run; validated before it reaches a command line."""

    run_id: str
    epoch_unix: float | None = None
    overrides: tuple[str, ...] = ()


def recording_id(fleet: str, run_id: str) -> str:
    """The Rerun recording id shared by every process of a run."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"phalanx/{fleet}/{run_id}"))


def _common(loaded: LoadedDeployment, host: str, run: RunParameters, identity: str) -> list[str]:
    spec = loaded.spec
    argv = ["--fleet", spec.fleet, "--clock", spec.clock, "--mode", "client"]
    argv += ["--connect", local_endpoint(spec, host)]
    if spec.secured:
        files = identity_files(loaded, identity, check=False)  # the daemon checked at start
        argv += ["--tls-ca", files.ca, "--tls-cert", files.cert, "--tls-key", files.key]
    argv += [f"--set={o}" for o in (*spec.overrides, *run.overrides)]
    telemetry = _telemetry(spec, run)
    if telemetry.url is not None:
        argv += ["--recording-id", str(telemetry.recording_id), "--telemetry-url", telemetry.url]
    return argv


def agent_spec(loaded: LoadedDeployment, robot_id: str, *, run: RunParameters) -> AgentSpec:
    """The spec of a robot's agent, built from the deployment alone: a client of its
    host's daemon, with its own certificate when secured; a robot on a driver runs from
    the run's epoch (to the millisecond, as the world's command line gives it).
    """
    spec, placement = loaded.spec, loaded.spec.placement(robot_id)
    tls = None
    if spec.secured:  # (the daemon checked every child's files at start)
        tls = identity_files(loaded, common_name("robot", robot_id), check=False)
    transport = TransportConfig(
        mode="client", connect=(local_endpoint(spec, placement.host),), tls=tls
    )
    driver = DriverChoice(name=loaded.driver_of(robot_id), settings=placement.settings)
    on_driver = driver.settings is not None
    epoch_s = round(run.epoch_unix, 3) if on_driver and run.epoch_unix is not None else None
    return AgentSpec(
        scenario=loaded.scenario_path, overrides=(*spec.overrides, *run.overrides),
        robot_id=robot_id, fleet=spec.fleet, clock=spec.clock, transport=transport,
        driver=driver, epoch_s=epoch_s, watchdog_s=placement.watchdog_s,
        telemetry=_telemetry(spec, run),
    )  # fmt: skip


def _telemetry(spec: Deployment, run: RunParameters) -> TelemetryTarget:
    """Every process streams to the deployment's viewer, if it names one."""
    if spec.telemetry.url is None:
        return TelemetryTarget()
    return TelemetryTarget(
        recording_id=recording_id(spec.fleet, run.run_id), url=spec.telemetry.url
    )


def world_argv(
    loaded: LoadedDeployment, *, run: RunParameters, out: Path, python: str
) -> list[str]:
    """The command line of the world, built from the deployment alone."""
    spec, world = loaded.spec, loaded.spec.world
    if world is None:
        raise ConfigError(f"deployment {spec.name!r} has no [world]")
    argv = [python, "-m", "phalanx", "world", str(loaded.scenario_path)]
    argv += _common(loaded, world.host, run, "world")
    argv += ["--speed", repr(world.speed), "--out", str(out)]
    argv.append("--recording" if world.recording else "--no-recording")
    if spec.clock == "realtime" and run.epoch_unix is not None:
        argv += ["--epoch", f"{run.epoch_unix:.3f}"]
    # robots on real drivers move on their own: the world records them, never moves them
    real = [r.id for r in spec.robots if loaded.driver_of(r.id) != "sim"]
    return argv + [arg for rid in real for arg in ("--observe", rid)]


def bridge_argv(loaded: LoadedDeployment, *, run: RunParameters, python: str) -> list[str]:
    """The command line of the deployment's ROS 2 bridge, built from the deployment
    alone: `phalanx ros2 --deployment` (the scenario, `[ros2]`, the fleet and a client
    of its host's daemon come from the file), the bridge's certificate when secured,
    the run's overrides, and where it meets ROS 2.
    """
    spec, bridge = loaded.spec, loaded.spec.ros2
    if bridge is None or bridge_host(spec) is None:
        raise ConfigError(f"deployment {spec.name!r} runs no ROS 2 bridge ([ros2] enabled)")
    argv = [python, "-m", "phalanx", "ros2", "--deployment", str(loaded.path)]
    if spec.secured:
        argv += ["--identity", common_name("viewer", bridge.identity)]
    argv += [f"--set={o}" for o in run.overrides]  # (the file's own: with the file)
    for endpoint in bridge.connect or (ROS_ROUTER,):
        argv += ["--ros-connect", endpoint]
    return argv
