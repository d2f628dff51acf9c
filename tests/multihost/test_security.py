"""A secured fleet (`[security] mode = "mtls"`) attacked: each test fails if its attack works.

Three host daemons on loopback `tls/` endpoints (no root needed) with the access-control
lists generated from the deployment; the attackers are plain Zenoh sessions holding what
an attacker could: no certificate, another CA's, an expired one, a robot's valid one, a
viewer's, another fleet's operator's, a stolen robot computer's host certificate. The
last test runs the paper wedge across namespaced hosts under mTLS (root only).
"""

from __future__ import annotations

import datetime as dt
import json
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import pytest
from fleetlab import terminate
from netlab import NetLab

from phalanx.analysis.metrics import run_metrics
from phalanx.core.config_files import apply_overrides, load_scenario
from phalanx.core.errors import DeploymentError, TransportError
from phalanx.hosts import pki
from phalanx.hosts.access import identities, identity_files
from phalanx.hosts.deployment import LoadedDeployment, load_deployment
from phalanx.hosts.fleet_client import FleetClient
from phalanx.hosts.protocol import SpawnRequest
from phalanx.hosts.request_auth import sign
from phalanx.hosts.wiring import client_transport, local_endpoint
from phalanx.runtime.batch import run_batch
from phalanx.wire.codec import decode, encode
from phalanx.wire.keys import alive_key, robot_key, status_key
from phalanx.wire.messages import Message, RobotFlags, RobotState, SenseFrame, VelocityCommand
from phalanx.wire.security import TlsFiles
from phalanx.wire.transport import FleetSession, TransportConfig, free_tcp_port

pytestmark = pytest.mark.integration
HOSTS = ("laptop", "robot-a", "robot-b")
PLACEMENT = {"r1": "robot-a", "r2": "robot-b", "r3": "robot-b"}
SECURITY = 'mode = "mtls"\noperators = ["alice"]\nviewers = ["bob"]\nmay_override = ["alice"]'
DURATION_S = 115.0  # past the deadlock reverse at t = 100 s
CLAIMS_RUN_S = 30.0  # the real-time run r3's certificate claims the lead in
M = TypeVar("M", bound=Message)


def _issue_all(folder: Path, loaded: LoadedDeployment) -> None:
    pki.init_ca(folder / "pki", fleet=loaded.spec.fleet)
    for ident in identities(loaded.spec):
        pki.issue(folder / "pki", ident.common_name, addresses=ident.addresses)
    pki.init_ca(folder / "other", fleet="other")  # another fleet's CA and its people
    pki.issue(folder / "other", "operator.alice")
    pki.issue(folder / "other", "robot.r1")
    expired = dt.datetime.now(dt.UTC) - dt.timedelta(days=10)  # ours, but over a week ago
    crt, key = pki.issue(folder / "pki", "viewer.expired", days=1, start=expired)
    crt.rename(folder / "expired.crt")
    key.rename(folder / "expired.key")


@dataclass
class SecuredFleet:
    """The daemons of a secured loopback deployment, and how to join it as anyone."""

    loaded: LoadedDeployment
    folder: Path
    daemons: Any

    def files(self, identity: str) -> TlsFiles:
        """TLS files of `identity` (a common name in the PKI folder, or a path prefix)."""
        return identity_files(self.loaded, identity)

    def session(self, files: TlsFiles | None, host: str = "laptop") -> FleetSession:
        """A client of `host`'s router presenting `files` (None: no certificate)."""
        ca = str(self.folder / "pki" / "ca.crt")
        tls = files or TlsFiles(ca=ca, cert="", key="")
        endpoint = local_endpoint(self.loaded.spec, host)
        cfg = TransportConfig(mode="client", connect=(endpoint,), tls=tls, open_timeout_s=1.0)
        if files is None:  # no certificate at all: only the CA to check the router's
            cfg = cfg.model_copy(update={"tls": None})
            return _no_cert_session(cfg, ca)
        return FleetSession(cfg)


def _no_cert_session(cfg: TransportConfig, ca: str) -> FleetSession:
    import zenoh

    from phalanx.wire.transport import zenoh_config

    conf = zenoh_config(cfg)
    conf.insert_json5("transport/link/tls", json.dumps({"root_ca_certificate": ca}))
    try:
        zenoh.open(conf).close()
    except Exception as exc:  # Zenoh's ZError: refused, as it must be
        raise TransportError(str(exc)) from exc
    raise AssertionError("a peer without a certificate joined the fleet")


@contextmanager
def _secured_fleet(kit: Any, folder: Path, *, clock: str) -> Iterator[SecuredFleet]:
    """A secured deployment on three loopback hosts, daemons running (stopped at the end)."""
    hosts = [(h, "127.0.0.1", free_tcp_port()) for h in HOSTS]
    text = kit.deployment_text(
        name="secured", hosts=hosts, out_dir=folder / "results", clock=clock,
        placement=PLACEMENT, world_host="laptop", lease_ms=1000, security=SECURITY,
    )  # fmt: skip
    path = folder / "secured.toml"
    path.write_text(text)
    loaded = load_deployment(path)
    _issue_all(folder, loaded)
    daemons = kit.start_daemons(path, HOSTS, folder / "logs")
    try:
        with FleetClient(loaded, _operator(loaded)) as client:
            client.wait_for_hosts(30.0, lambda _text: None)
        yield SecuredFleet(loaded, folder, daemons)
    finally:
        codes = daemons.stop()
        assert codes == dict.fromkeys(HOSTS, 0), daemons.log_tail()


@pytest.fixture(scope="module")
def secured(module_kit: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[SecuredFleet]:
    """The secured deployment in lockstep, shared by the module's tests."""
    with _secured_fleet(module_kit, tmp_path_factory.mktemp("secured"), clock="lockstep") as made:
        yield made


@pytest.fixture
def secured_realtime(kit: Any, tmp_path: Path) -> Iterator[SecuredFleet]:
    """The same deployment on the real-time clock, where every robot hears every robot's
    flags (in lockstep the world's frames carry the states leadership is decided on)."""
    with _secured_fleet(kit, tmp_path, clock="realtime") as made:
        yield made


def _operator(loaded: LoadedDeployment, identity: str = "operator.alice") -> TransportConfig:
    return client_transport(loaded.spec, via="laptop", tls=identity_files(loaded, identity))


class Observer:
    """What a legitimate reader (viewer.bob, on the laptop) receives: keys and tokens."""

    def __init__(self, fleet: SecuredFleet) -> None:
        self.session = fleet.session(fleet.files("viewer.bob"))
        self.keys: list[tuple[str, bytes]] = []
        self.tokens: set[str] = set()
        self._lock = threading.Lock()
        prefix = f"phalanx/{fleet.loaded.spec.fleet}"
        self.session.hold(self.session.zenoh.declare_subscriber(f"{prefix}/**", self._on_sample))
        self.session.watch_alive(f"{prefix}/alive/*", self._on_token)

    def _on_sample(self, sample: Any) -> None:
        with self._lock:
            self.keys.append((str(sample.key_expr), sample.payload.to_bytes()))

    def _on_token(self, key: str, alive: bool) -> None:
        with self._lock:
            (self.tokens.add if alive else self.tokens.discard)(key)

    def seen(self, marker: bytes) -> list[str]:
        """Keys of samples whose payload holds `marker`."""
        with self._lock:
            return [key for key, payload in self.keys if marker in payload]

    def count(self) -> int:
        """How many samples arrived so far (a point to read `decoded` from)."""
        with self._lock:
            return len(self.keys)

    def decoded(self, model: type[M], key: str, start: int = 0) -> list[M]:
        """The valid `model`s that arrived on `key`, from sample `start` on."""
        with self._lock:
            payloads = [payload for k, payload in self.keys[start:] if k == key]
        return [m for m in (decode(model, p) for p in payloads) if m is not None]


def _forgeries(fleet: str, stamp_s: float) -> list[tuple[str, bytes]]:
    """What r3's certificate would publish to take the fleet over (valid messages on the
    other robots' keys; r3's own keys are its own: a robot lying about itself is not
    something access control can stop, docs/SECURITY.md)."""
    flags = RobotFlags.model_construct(
        robot_id="r2", seq=10**6, stamp_s=stamp_s, fsm_state="NAVIGATE", epoch=1000,
        formation_leader_id="r2", clear=True, formed=True,
    )  # fmt: skip
    state = RobotState.model_construct(
        robot_id="r2", seq=10**6, stamp_s=stamp_s, x_m=1.8, y_m=1.8, theta_rad=0.0,
        v_mps=0.3, omega_radps=0.0, fsm_state="NAVIGATE",
    )  # fmt: skip
    leader = RobotState.model_construct(**{**state.__dict__, "robot_id": "r1"})
    cmd = VelocityCommand.model_construct(
        robot_id="r2", tick=1, stamp_s=stamp_s, v_mps=0.3, omega_radps=1.0
    )
    frame = SenseFrame.model_construct(
        robot_id="r2", tick=1, t_s=0.1, dt_s=0.1, x_m=0.0, y_m=0.0, theta_rad=0.0, v_mps=0.0,
        omega_radps=0.0, sonar_ranges_m=(0.1,) * 16, bumpers=(), final=True,
    )  # fmt: skip
    return [
        (robot_key(fleet, "r2", "flags"), encode(flags)),  # r2 "claims" the lead at epoch 1000
        (robot_key(fleet, "r2", "state"), encode(state)),
        (robot_key(fleet, "r1", "state"), encode(leader)),  # a forged leader for followers
        (robot_key(fleet, "r2", "cmd"), encode(cmd)),  # drives the simulated r2
        (robot_key(fleet, "r2", "sense"), encode(frame)),  # ground truth: the world's only
    ]


# --- the attacks ----------------------------------------------------------------------


def test_a_peer_without_a_certificate_cannot_join(secured: SecuredFleet) -> None:
    with pytest.raises(TransportError):
        secured.session(None)
    plain = TransportConfig(
        mode="client", connect=(f"tcp/127.0.0.1:{secured.loaded.spec.port_of('laptop')}",),
        open_timeout_s=1.0,
    )  # fmt: skip
    with pytest.raises(TransportError):
        FleetSession(plain).close()  # plain TCP on the TLS port: no session either


@pytest.mark.parametrize(
    "identity", ["other/robot.r1", "other/operator.alice", "expired"], ids=["other-ca-robot",
    "other-fleet-operator", "expired"],
)  # fmt: skip
def test_a_certificate_of_another_ca_or_expired_cannot_join(
    secured: SecuredFleet, identity: str
) -> None:
    files = secured.files(str(secured.folder / identity))
    with pytest.raises(TransportError):
        secured.session(files).close()


def test_a_robot_certificate_cannot_speak_for_another_robot(secured: SecuredFleet) -> None:
    fleet = secured.loaded.spec.fleet
    observer = Observer(secured)
    forger = secured.session(secured.files("robot.r3"), host="robot-b")  # r3's own host
    try:
        time.sleep(0.5)
        forger.declare_alive(alive_key(fleet, "r2"))  # would block r2's start
        forger.serve_status(status_key(fleet, "r2"), lambda: {"forged": True})
        marker = b"own-key-control"
        for _ in range(5):
            forger.publish_raw(robot_key(fleet, "r3", "event"), marker)  # allowed: its own key
            for key, payload in _forgeries(fleet, 1.0):
                forger.publish_raw(key, payload)
            time.sleep(0.05)
        deadline = time.monotonic() + 3.0
        while not observer.seen(marker) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert observer.seen(marker), "the observer hears r1's own keys (the control)"
        forged = {key for key, _ in _forgeries(fleet, 1.0)}
        arrived = {key for key, _ in observer.keys}
        assert not forged & arrived, forged & arrived
        assert alive_key(fleet, "r2") not in observer.tokens
        assert observer.session.query_status(status_key(fleet, "r2"), 1.0) == []
    finally:
        forger.close()
        observer.session.close()


def test_a_viewer_can_look_but_not_start_or_stop(secured: SecuredFleet) -> None:
    loaded = secured.loaded
    with FleetClient(loaded, _operator(loaded, "viewer.bob")) as viewer:
        statuses = viewer.statuses()
        assert all(s is not None for s in statuses.values())  # `phalanx status` works
        with pytest.raises(DeploymentError, match="no answer"):
            viewer.spawn("viewer1", overrides=(), epoch_unix=None)
        assert all(r is None for r in viewer.stop().values())
        after = viewer.statuses()
    assert all(s is not None and s.children == () for s in after.values()), after


def test_a_stolen_host_certificate_cannot_relay_an_outsiders_request(
    secured: SecuredFleet,
) -> None:
    """A robot computer's host key forwards queries (operators may reach any daemon through
    any host); the daemon still refuses a request no listed operator of this fleet signed.
    """
    loaded = secured.loaded
    request = SpawnRequest(
        deployment=loaded.spec.name, digest=loaded.digest, run_id="stolen",
        overrides=("navigation.reactive=false",), issued_unix=time.time(),
    ).model_dump_json().encode()  # fmt: skip
    outsider = secured.files(str(secured.folder / "other" / "operator.alice"))
    viewer = secured.files("viewer.bob")
    with FleetClient(loaded, _operator(loaded, "host.robot-a")) as stolen:
        for payload, reason in [
            (request, "unsigned request"),
            (sign(request, outsider), "not signed by this fleet's CA"),
            (sign(request, viewer), "may not start or stop"),
        ]:
            reply = stolen.ask("spawn", {"laptop": payload}, timeout_s=5.0)["laptop"]
            assert reply is not None
            assert not reply.ok
            assert reason in reply.error, reply.error
            assert reply.status.children == ()


@pytest.mark.timeout(260)  # its child processes' own bound, and set-up
def test_the_fleet_runs_unchanged_while_a_robot_certificate_attacks_it(
    kit: Any, secured: SecuredFleet, same_follower_metrics: Callable[..., None]
) -> None:
    """The paper wedge, launched by operator alice, while r3's certificate floods the
    forged leadership claim, leader and follower states, commands and sense frames, and
    holds r2's liveliness token: the run is the single-process run to 1e-6.
    """
    fleet = secured.loaded.spec.fleet
    forger = secured.session(secured.files("robot.r3"), host="robot-b")
    forger.declare_alive(alive_key(fleet, "r2"))
    stop = threading.Event()

    def attack() -> None:
        stamp = 0.0
        while not stop.is_set():
            stamp += 0.05
            for key, payload in _forgeries(fleet, stamp):
                forger.publish_raw(key, payload)
            stop.wait(0.02)

    attacker = threading.Thread(target=attack, daemon=True)
    attacker.start()
    try:
        launched = subprocess.run(
            [
                *kit.CLI, "launch", str(secured.loaded.path), "--identity", "operator.alice",
                "--set", f"duration_s={DURATION_S}", "--run-id", "attacked", "--no-table",
                "--host-wait", "30", "--timeout", "150", "--via", "laptop",
            ],
            capture_output=True, text=True, timeout=200, check=False,
        )  # fmt: skip
    finally:
        stop.set()
        attacker.join(5)
        forger.close()
    context = launched.stdout[-3000:] + launched.stderr[-2000:]
    assert launched.returncode == 0, context + secured.daemons.log_tail()
    results = secured.folder / "results" / "attacked" / "metrics.json"
    multi = json.loads(results.read_text())
    scenario = apply_overrides(load_scenario(kit.WEDGE), [f"duration_s={DURATION_S}"])
    same_follower_metrics(multi, run_metrics(run_batch(scenario)))


def _states(observer: Observer, fleet: str, start: int = 0) -> dict[str, list[RobotState]]:
    """Every robot's states the observer heard, from sample `start` on."""
    return {r: observer.decoded(RobotState, robot_key(fleet, r, "state"), start) for r in PLACEMENT}


def _until(predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Whether `predicate` held within `timeout_s` (polled every 50 ms)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def _claim(observer: Observer, forger: FleetSession, fleet: str, epoch: int) -> None:
    """r3's certificate claims the lead under `epoch` on r3's own flags key (20 packets,
    each stamped ahead of the fleet's newest state, as the local fleet's test does)."""
    for _ in range(20):
        now = max(s[-1].stamp_s for s in _states(observer, fleet).values() if s)
        forged = RobotFlags(
            robot_id="r3", seq=10**6, stamp_s=now + 0.3, fsm_state="FORMATION_TRACK",
            epoch=epoch, formation_leader_id="r3", clear=True,
        )  # fmt: skip
        forger.publish_raw(robot_key(fleet, "r3", "flags"), encode(forged, "packed"))
        time.sleep(0.05)


@pytest.mark.slow
@pytest.mark.timeout(300)  # the daemons, a 30 s run, the launcher's own bounds
def test_a_robot_certificate_cannot_take_the_lead_with_its_own_flags(
    kit: Any, secured_realtime: SecuredFleet
) -> None:
    """Row 4 of the issue under mTLS. r3's certificate may publish r3's own flags (access
    control lets them through: the observer hears them), so only the acceptance rule
    (`Leadership.verdict`) stands between r3's claim and the lead: claims at epoch 1 (the
    next, as a real handover carries) and 1000 while r1 lives. Every robot follows r1
    under epoch 0 throughout; r1 and r2 count the refusals. (Before: everyone followed r3.)
    """
    secured = secured_realtime
    fleet = secured.loaded.spec.fleet
    observer = Observer(secured)
    forger = secured.session(secured.files("robot.r3"), host="robot-b")
    log_path = secured.folder / "launch.log"
    argv = [
        *kit.CLI, "launch", str(secured.loaded.path), "--identity", "operator.alice",
        "--set", f"duration_s={CLAIMS_RUN_S}", "--run-id", "claims", "--no-table",
        "--host-wait", "30", "--timeout", str(CLAIMS_RUN_S + 60), "--via", "laptop",
    ]  # fmt: skip
    with log_path.open("wb") as sink:
        launch = subprocess.Popen(argv, stdout=sink, stderr=subprocess.STDOUT)
    try:

        def tracking() -> bool:
            states = _states(observer, fleet)
            return all(
                len(states[r]) >= 20 and states[r][-1].fsm_state == "FORMATION_TRACK"
                for r in ("r2", "r3")
            )

        assert _until(tracking, 60.0), log_path.read_text()[-3000:]
        start = observer.count()
        _claim(observer, forger, fleet, 1)
        _claim(observer, forger, fleet, 1000)
        claimed = max(s[-1].stamp_s for s in _states(observer, fleet).values())

        def went_on() -> bool:  # every robot published for a second after the claims
            states = _states(observer, fleet, start).values()
            return all(s and s[-1].stamp_s > claimed + 1.0 for s in states)

        assert _until(went_on, 30.0)
        statuses = {
            r: observer.session.query_status(status_key(fleet, r), 2.0) for r in ("r1", "r2")
        }
        code = launch.wait(CLAIMS_RUN_S + 90)
    finally:
        terminate([launch], grace_s=30.0)
        forger.close()
        observer.session.close()
    heard = observer.decoded(RobotFlags, robot_key(fleet, "r3", "flags"), start)
    assert {f.epoch for f in heard if f.formation_leader_id == "r3"} == {1, 1000}  # the control
    followed = {
        (s.robot_id, s.formation_leader_id, s.epoch)
        for states in _states(observer, fleet, start).values()
        for s in states
    }
    assert followed == {("r1", "r1", 0), ("r2", "r1", 0), ("r3", "r1", 0)}, followed
    for rid, replies in statuses.items():  # the claims were heard, refused and counted
        assert len(replies) == 1, (rid, replies)
        assert replies[0]["leader_claims_refused"] > 0, replies[0]
        assert replies[0]["decode"]["rejected"].get("RobotFlags", 0) > 0, replies[0]
    assert code == 0, log_path.read_text()[-3000:] + secured.daemons.log_tail()


# --- across namespaces ----------------------------------------------------------------


@pytest.mark.timeout(260)  # its child processes' own bound, and set-up
def test_lockstep_across_namespaces_under_mtls_gives_the_single_host_metrics(
    kit: Any, lab: NetLab, tmp_path: Path, same_follower_metrics: Callable[..., None]
) -> None:
    """The netns tier's lockstep run (test_netns_fleet.py, open links) under mTLS: every
    link `tls/` with certificates checked, each host's access-control list applied.
    """
    hosts = [(h, lab.address(h), 7447) for h in kit.LAB_HOSTS]
    text = kit.deployment_text(
        name="nsmtls", hosts=hosts, out_dir=tmp_path / "results", clock="lockstep",
        security=SECURITY,
    )  # fmt: skip
    path = tmp_path / "nsmtls.toml"
    path.write_text(text)
    loaded = load_deployment(path)
    _issue_all(tmp_path, loaded)
    daemons = kit.start_daemons(path, kit.LAB_HOSTS, tmp_path / "logs", wrap=lab.command)
    try:
        launched = subprocess.run(
            lab.command("world", [
                *kit.CLI, "launch", str(path), "--identity", "operator.alice",
                "--set", f"duration_s={DURATION_S}", "--run-id", "tls1", "--no-table",
                "--host-wait", "60", "--timeout", "150",
            ]),
            capture_output=True, text=True, timeout=200, check=False,
        )  # fmt: skip
    finally:
        codes = daemons.stop()
    context = launched.stdout[-3000:] + launched.stderr[-2000:] + daemons.log_tail()
    assert launched.returncode == 0, context
    assert codes == dict.fromkeys(kit.LAB_HOSTS, 0), context
    multi = json.loads((tmp_path / "results" / "tls1" / "metrics.json").read_text())
    scenario = apply_overrides(load_scenario(kit.WEDGE), [f"duration_s={DURATION_S}"])
    same_follower_metrics(multi, run_metrics(run_batch(scenario)))
