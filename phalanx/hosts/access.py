"""Who may do what on a deployment's fabric: identities, their files, and the access-control
list every host's router applies, all derived from the deployment file.

Default deny. At host H's router, by certificate common name:

- `robot.<id>` (only the robots H runs): publish on its own robot's `state`, `flags`,
  `cmd`, `event`, `report`, `scan` and on `leader`; hold its own liveliness token; serve its
  own status;
- `world` (only if H runs it): publish sense frames, pose fixes and relative
  sightings (the ground truth a simulated robot sees); hold `alive/world`; serve its
  status;
- `operator.<name>` (listed in `[security] operators`): query the host daemons'
  `spawn`, `stop`, `status` and every process's status;
- `viewer.<name>` (listed in `viewers`): query status only;
- `host.<other>` (the other hosts' routers): carry what their own processes may send
  (the robots and world placed there, their daemon's token, queryables and log lines),
  and forward queries to the daemons (an operator's identity is checked again by the
  daemon itself, on the request's signature: `phalanx.hosts.request_auth`);
- `viewer.<identity>` of an enabled `[ros2]` (at its host's router: `ros2.host`, else the
  world's): publish exactly the ROS 2 bridge's data keys, hold its node's, publishers'
  and subscriptions' liveliness tokens, and serve its transient-local topics' caches
  (`phalanx.ros2.topics.bridge_keys`); with `[ros2] inputs`, publish on every robot's
  `operator` key (what ROS 2's operator asks of the robot that leads), and on no other
  key of the fleet; the other hosts' routers carry the same from that host;
- every identity of the fleet may subscribe to and receive anything under the fleet's
  prefix, and the bridge's ROS keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from phalanx.core.errors import ConfigError
from phalanx.hosts.deployment import Deployment, LoadedDeployment, SecuritySettings
from phalanx.hosts.pki import common_name
from phalanx.wire.security import READS, AccessControl, AclPolicy, AclRule, TlsFiles

if TYPE_CHECKING:
    from phalanx.ros2.topics import BridgeKeys

ROBOT_TOPICS = ("state", "flags", "cmd", "event", "report", "scan", "truth")
WORLD_TOPICS = ("sense", "fix", "relative")
EVERYTHING = (
    "put", "delete", "reply", "query", "liveliness_token", "declare_subscriber",
    "declare_queryable", "declare_liveliness_subscriber", "liveliness_query",
)  # fmt: skip


def security_of(spec: Deployment) -> SecuritySettings:
    """The deployment's `[security]` table (its defaults if the file has none)."""
    return spec.security or SecuritySettings()


def pki_dir(loaded: LoadedDeployment) -> Path:
    """The deployment's PKI folder (relative paths: to the deployment file)."""
    return (loaded.path.parent / security_of(loaded.spec).pki).resolve()


def ca_path(loaded: LoadedDeployment) -> Path:
    """The fleet CA's certificate."""
    ca = security_of(loaded.spec).ca
    return (loaded.path.parent / ca).resolve() if ca else pki_dir(loaded) / "ca.crt"


def identity_files(loaded: LoadedDeployment, identity: str, *, check: bool = True) -> TlsFiles:
    """The TLS files of `identity`: a common name in the PKI folder (`operator.alice`), or
    a path without its suffix (`/etc/phalanx/operator.alice`). ConfigError, saying how to
    issue them, if one is missing and `check`.
    """
    base = Path(identity) if "/" in identity else pki_dir(loaded) / identity
    files = TlsFiles(
        ca=str(ca_path(loaded)), cert=str(base.with_name(base.name + ".crt")),
        key=str(base.with_name(base.name + ".key")),
    )  # fmt: skip
    if check:
        _check_files(loaded, files, base.name)
    return files


def host_files(loaded: LoadedDeployment, host: str, *, check: bool = True) -> TlsFiles:
    """Host `host`'s TLS files (its `cert`/`key` in the file, else `<pki>/host.<name>.*`)."""
    entry = loaded.spec.host(host)
    if entry.cert is None and entry.key is None:
        return identity_files(loaded, common_name("host", host), check=check)
    default = identity_files(loaded, common_name("host", host), check=False)
    here = loaded.path.parent
    files = TlsFiles(
        ca=default.ca,
        cert=str((here / entry.cert).resolve()) if entry.cert else default.cert,
        key=str((here / entry.key).resolve()) if entry.key else default.key,
    )
    if check:
        _check_files(loaded, files, f"host.{host}")
    return files


def _check_files(loaded: LoadedDeployment, files: TlsFiles, cn: str) -> None:
    for path in (files.ca, files.cert, files.key):
        if not Path(path).is_file():
            raise ConfigError(
                f"{loaded.path}: security mode 'mtls' needs {path} (identity {cn}): issue it "
                f"with `phalanx pki issue {pki_dir(loaded)} {cn}` or `phalanx pki issue "
                f"{pki_dir(loaded)} --deployment {loaded.path}`"
            )


@dataclass(frozen=True)
class Identity:
    """A certificate a deployment needs: its common name and the addresses it serves."""

    common_name: str
    addresses: tuple[str, ...] = ()


def identities(spec: Deployment) -> list[Identity]:
    """Every identity the deployment names: hosts (with their addresses), robots, the
    world, operators and viewers.
    """
    found = [
        Identity(common_name("host", h.name), tuple(a for a in (h.address, h.bind) if a))
        for h in spec.hosts
    ]
    found += [Identity(common_name("robot", r.id)) for r in spec.robots]
    if spec.world is not None:
        found.append(Identity("world"))
    security = security_of(spec)
    found += [Identity(common_name("operator", n)) for n in security.operators]
    found += [Identity(common_name("viewer", n)) for n in security.viewers]
    if spec.ros2 is not None and spec.ros2.enabled:
        bridge = Identity(common_name("viewer", spec.ros2.identity))
        found += [] if bridge in found else [bridge]
    return found


# --- the ROS 2 bridge -------------------------------------------------------------------


def bridge_host(spec: Deployment) -> str | None:
    """The host whose daemon the deployment's ROS 2 bridge joins (None: it runs none)."""
    if spec.ros2 is None or not spec.ros2.enabled:
        return None
    world = spec.world.host if spec.world is not None else spec.hosts[0].name
    return spec.ros2.host or world


def bridge_keys(spec: Deployment) -> BridgeKeys | None:
    """The keys the deployment's ROS 2 bridge originates (None: it runs none)."""
    if spec.ros2 is None or bridge_host(spec) is None:
        return None
    from phalanx.ros2.topics import bridge_keys as keys_of

    return keys_of(spec.ros2, [r.id for r in spec.robots])


def operator_keys(spec: Deployment) -> list[str]:
    """The fleet's keys the deployment's ROS 2 bridge publishes on: every robot's
    `operator` (the robot that leads is any of them), if it takes anything from ROS 2.
    """
    if spec.ros2 is None or bridge_host(spec) is None or not spec.ros2.inputs:
        return []
    return [f"phalanx/{spec.fleet}/robot/{r.id}/operator" for r in spec.robots]


def _bridge_rules(rule_id: str, keys: BridgeKeys, operator: list[str]) -> list[AclRule]:
    """What the bridge (or the router of its host) may originate: exactly its keys."""
    rules = [
        _allow(f"{rule_id}-put", ("put",), [*keys.puts, *operator]),
        _allow(f"{rule_id}-token", ("liveliness_token",), list(keys.tokens)),
    ]
    if keys.caches:
        cache_kinds = ("put", "liveliness_token", "declare_queryable", "reply")
        rules.append(_allow(f"{rule_id}-cache", cache_kinds, list(keys.caches)))
    return rules


def _ros_reads(keys: BridgeKeys | None) -> list[AclRule]:
    """Every identity may subscribe to the bridge's keys and receive them."""
    if keys is None:
        return []
    return [
        _allow("ros-read", (*READS, "query"), list(keys.all())),
        _allow("ros-receive", EVERYTHING, list(keys.all()), flow="egress"),
    ]


# --- the access-control list ------------------------------------------------------------


def _allow(
    rule_id: str, messages: tuple[str, ...], keys: list[str], flow: str = "ingress"
) -> AclRule:
    return AclRule.model_validate(
        {"id": rule_id, "messages": messages, "flows": (flow,), "key_exprs": tuple(keys)}
    )


def _origin(spec: Deployment, host: str) -> dict[str, list[str]]:
    """What the processes of `host` may originate, by message kind."""
    prefix = f"phalanx/{spec.fleet}"
    robots = spec.robots_on(host)
    puts = [f"{prefix}/robot/{r}/{t}" for r in robots for t in ROBOT_TOPICS]
    puts += [f"{prefix}/leader"] if robots else []
    names = [*robots, *(["world"] if spec.runs_world(host) else [])]
    if spec.runs_world(host):
        puts += [f"{prefix}/robot/*/{t}" for t in WORLD_TOPICS]
    return {
        "put": puts,
        "liveliness_token": [f"{prefix}/alive/{n}" for n in names],
        "declare_queryable": [f"{prefix}/status/{n}" for n in names],
    }


def _process_policy(spec: Deployment, host: str, cn: str, names: list[str]) -> list[AclRule]:
    """The rules of one process (a robot's agent or the world) on `host`."""
    prefix = f"phalanx/{spec.fleet}"
    robots = [n for n in names if n != "world"]
    puts = [f"{prefix}/robot/{r}/{t}" for r in robots for t in ROBOT_TOPICS]
    puts += [f"{prefix}/leader"] if robots else []
    if "world" in names:
        puts += [f"{prefix}/robot/*/{t}" for t in WORLD_TOPICS]
    return [
        _allow(f"{cn}-put", ("put",), puts),
        _allow(f"{cn}-token", ("liveliness_token",), [f"{prefix}/alive/{n}" for n in names]),
        _allow(f"{cn}-status", ("declare_queryable",), [f"{prefix}/status/{n}" for n in names]),
    ]


def host_acl(spec: Deployment, host: str) -> AccessControl:
    """The access-control list of host `host`'s router."""
    spec.host(host)
    prefix = f"phalanx/{spec.fleet}"
    everyone = f"{prefix}/**"
    ros = bridge_keys(spec)
    common = [
        _allow("read", READS, [everyone]),
        _allow("reply", ("reply",), [everyone]),
        _allow("receive", EVERYTHING, [everyone], flow="egress"),
        *_ros_reads(ros),
    ]
    policies: list[AclPolicy] = []
    for rid in spec.robots_on(host):
        cn = common_name("robot", rid)
        policies.append(_policy(cn, [cn], [*_process_policy(spec, host, cn, [rid]), *common]))
    if spec.runs_world(host):
        policies.append(
            _policy("world", ["world"], [*_process_policy(spec, host, "world", ["world"]), *common])
        )
    security = security_of(spec)
    status_keys = [f"{prefix}/host/*/status", f"{prefix}/status/*"]
    if security.operators:
        names = [common_name("operator", n) for n in security.operators]
        control = [f"{prefix}/host/*/spawn", f"{prefix}/host/*/stop", *status_keys]
        rules = [_allow("control", ("query",), control), *common]
        policies.append(_policy("operators", names, rules))
    if security.viewers:
        names = [common_name("viewer", n) for n in security.viewers]
        rules = [_allow("look", ("query",), status_keys), *common]
        policies.append(_policy("viewers", names, rules))
    if ros is not None and spec.ros2 is not None and bridge_host(spec) == host:
        cn = common_name("viewer", spec.ros2.identity)
        rules = _bridge_rules("ros2", ros, operator_keys(spec))
        policies.append(_policy("ros2", [cn], [*rules, *common]))
    for other in spec.hosts:
        if other.name != host:
            policies.append(_peer_host_policy(spec, other.name, common))
    return AccessControl(policies=tuple(policies))


def _peer_host_policy(spec: Deployment, other: str, common: list[AclRule]) -> AclPolicy:
    prefix = f"phalanx/{spec.fleet}"
    cn = common_name("host", other)
    origin = _origin(spec, other)
    daemon = f"{prefix}/host/{other}"
    rules = [
        _allow(f"{cn}-put", ("put",), [*origin["put"], f"{daemon}/log/**"]),
        _allow(
            f"{cn}-token", ("liveliness_token",), [*origin["liveliness_token"], f"{daemon}/alive"]
        ),
        _allow(
            f"{cn}-queryables",
            ("declare_queryable",),
            [*origin["declare_queryable"], f"{daemon}/spawn", f"{daemon}/stop", f"{daemon}/status"],
        ),
        _allow(f"{cn}-forward", ("query",), [f"{prefix}/host/*/*", f"{prefix}/status/*"]),
        *common,
    ]
    ros = bridge_keys(spec)
    if ros is not None and bridge_host(spec) == other:
        rules += _bridge_rules(f"{cn}-ros2", ros, operator_keys(spec))
    return _policy(cn, [cn], rules)


def _policy(policy_id: str, names: list[str], rules: list[AclRule]) -> AclPolicy:
    # Rules with the same id must be the same rule: the shared ones are.
    return AclPolicy(id=policy_id, names=tuple(names), rules=tuple(r for r in rules if r.key_exprs))


def describe_acls(spec: Deployment) -> str:
    """Every host's access-control list, as `phalanx launch --print-acl` prints it."""
    parts = []
    for entry in spec.hosts:
        parts.append(f"# host {entry.name} (its router, tls/ links, default deny)")
        parts.append(host_acl(spec, entry.name).describe())
    return "\n".join(parts)
