"""The fleet's PKI, the access-control list generated from a deployment, signed requests
to host daemons and the overrides a daemon accepts."""

from __future__ import annotations

import datetime as dt
import json
import stat
import time
from pathlib import Path

import pytest

from phalanx.core.config_files import CONFIG_ROOT
from phalanx.core.errors import ConfigError, RequestRefused
from phalanx.hosts import pki
from phalanx.hosts.access import host_acl, identities, identity_files
from phalanx.hosts.daemon import HostDaemon
from phalanx.hosts.deployment import load_deployment
from phalanx.hosts.protocol import SpawnRequest
from phalanx.hosts.request_auth import RequestVerifier, sign
from phalanx.hosts.wiring import client_identity, host_listen, secured_host_transport

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


def _deployment(folder: Path, security: str = "") -> Path:
    text = f"""name = "sec"
fleet = "sec"
scenario = "{WEDGE}"
{security}
[[hosts]]
name = "laptop"
address = "192.0.2.10"
[[hosts]]
name = "robot-a"
address = "192.0.2.11"
[world]
host = "laptop"
[[robots]]
id = "r1"
host = "robot-a"
[[robots]]
id = "r2"
host = "robot-a"
[[robots]]
id = "r3"
host = "laptop"
"""
    path = folder / "sec.toml"
    path.write_text(text)
    return path


SECURITY = '[security]\noperators = ["alice", "root"]\nviewers = ["bob"]\nmay_override = ["root"]'


@pytest.fixture(scope="module")
def issued(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A deployment with its PKI folder, every identity issued, and a CA of another fleet."""
    folder = tmp_path_factory.mktemp("sec")
    path = _deployment(folder, SECURITY)
    pki.init_ca(folder / "pki", fleet="sec")
    for ident in identities(load_deployment(path).spec):
        pki.issue(folder / "pki", ident.common_name, addresses=ident.addresses)
    pki.init_ca(folder / "other", fleet="other")
    pki.issue(folder / "other", "operator.alice")
    return path


def test_keys_are_readable_by_their_owner_only_and_names_carry_the_role(issued: Path) -> None:
    folder = issued.parent / "pki"
    for key in folder.glob("*.key"):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    listed = {i.common_name: i for i in pki.list_issued(folder)}
    assert set(listed) >= {"host.laptop", "host.robot-a", "robot.r1", "world", "operator.alice"}
    assert "192.0.2.11" in listed["host.robot-a"].names  # TLS checks the name dialled
    assert "127.0.0.1" in listed["host.robot-a"].names  # its own processes dial loopback
    assert not any(i.expired() for i in listed.values())


def test_the_pki_refuses_bad_names_lost_cas_and_overwriting_a_ca(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no CA here"):
        pki.issue(tmp_path, "robot.r1")
    pki.init_ca(tmp_path, fleet="x")
    with pytest.raises(ConfigError, match="invalidate"):
        pki.init_ca(tmp_path, fleet="x")
    for bad in ("r1", "robot.", "admin.x", "robot.r1/../x", "host.a b"):
        with pytest.raises(ConfigError, match=r"expected robot\.ID"):
            pki.issue(tmp_path, bad)


def test_an_expired_certificate_or_another_ca_fails_the_chain(issued: Path, tmp_path: Path) -> None:
    folder = issued.parent / "pki"
    ca = folder / "ca.crt"
    assert pki.verify_chain((folder / "robot.r1.crt").read_bytes(), ca) == "robot.r1"
    with pytest.raises(ConfigError, match=r"another CA|not signed"):
        pki.verify_chain((issued.parent / "other" / "operator.alice.crt").read_bytes(), ca)
    pki.init_ca(tmp_path, fleet="t")
    start = dt.datetime.now(dt.UTC) - dt.timedelta(days=3)
    crt, _ = pki.issue(tmp_path, "robot.r1", days=1, start=start)
    assert pki.read_issued(crt).expired()
    with pytest.raises(ConfigError, match="validity"):
        pki.verify_chain(crt.read_bytes(), tmp_path / "ca.crt")


def test_a_deployment_is_secured_by_default_unless_on_one_machine(tmp_path: Path) -> None:
    spec = load_deployment(_deployment(tmp_path)).spec
    assert spec.secured
    assert host_listen(spec, "robot-a") == ("tls/192.0.2.11:7447", "tls/127.0.0.1:7447")
    loopback = load_deployment("loopback").spec
    assert not loopback.secured
    assert loopback.open_warning is None
    opened = load_deployment(_deployment(tmp_path, '[security]\nmode = "open"')).spec
    assert not opened.secured
    assert "WARNING" in (opened.open_warning or "")


def test_missing_files_are_named_with_the_command_that_issues_them(tmp_path: Path) -> None:
    loaded = load_deployment(_deployment(tmp_path))
    with pytest.raises(ConfigError, match=r"phalanx pki issue .*host\.robot-a"):
        secured_host_transport(loaded, "robot-a")


def test_the_acl_lets_each_robot_publish_only_its_own_keys(issued: Path) -> None:
    spec = load_deployment(issued).spec
    acl = host_acl(spec, "robot-a").zenoh_json()
    assert acl["default_permission"] == "deny"
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    rules = {r["id"]: r for r in acl["rules"]}
    policy = {p["id"]: p["rules"] for p in acl["policies"]}
    assert subjects["s-robot.r1"] == ["robot.r1"]
    r1_puts = rules["robot.r1-put"]["key_exprs"]
    assert "phalanx/sec/robot/r1/state" in r1_puts
    assert not any("/r2/" in k or "/sense" in k for k in r1_puts)
    assert rules["robot.r1-token"]["key_exprs"] == ["phalanx/sec/alive/r1"]
    assert "s-robot.r3" not in subjects  # r3 runs on the laptop: not a subject here
    laptop = {r["id"]: r for r in host_acl(spec, "laptop").zenoh_json()["rules"]}
    assert "phalanx/sec/robot/*/sense" in laptop["world-put"]["key_exprs"]
    assert "phalanx/sec/host/*/spawn" in laptop["control"]["key_exprs"]
    assert not any("spawn" in k for k in laptop["look"]["key_exprs"])  # viewers
    peer = laptop["host.robot-a-put"]["key_exprs"]  # robot-a may carry r1, r2 only
    assert "phalanx/sec/robot/r2/flags" in peer
    assert "phalanx/sec/robot/r3/flags" not in peer
    assert "look" in policy["viewers"]
    assert "control" not in policy["viewers"]
    json.dumps(acl)  # what goes into Zenoh's configuration


def _request(**values: object) -> bytes:
    request = SpawnRequest.model_validate(
        {"deployment": "sec", "digest": "0" * 64, "run_id": "x", "issued_unix": time.time()}
        | values
    )
    return request.model_dump_json().encode()


def test_a_request_counts_only_signed_by_a_listed_operator_once(issued: Path) -> None:
    loaded = load_deployment(issued)
    folder = issued.parent / "pki"
    verifier = RequestVerifier(folder / "ca.crt", ("alice", "root"), 30.0)
    payload = sign(_request(), identity_files(loaded, "operator.alice"))
    name, inner = verifier.open(payload)
    assert name == "alice"
    assert SpawnRequest.model_validate_json(inner).run_id == "x"
    with pytest.raises(RequestRefused, match="replay"):
        verifier.open(payload)
    with pytest.raises(RequestRefused, match="unsigned"):
        verifier.open(_request())
    with pytest.raises(RequestRefused, match="may not start"):
        verifier.open(sign(_request(), identity_files(loaded, "viewer.bob")))
    foreign = identity_files(loaded, str(issued.parent / "other" / "operator.alice"))
    with pytest.raises(RequestRefused, match="refused"):
        verifier.open(sign(_request(), foreign))
    forged = json.loads(sign(_request(), identity_files(loaded, "operator.alice")))
    forged["request"] = json.loads(payload)["request"]  # another request under this signature
    with pytest.raises(RequestRefused, match="does not match"):
        verifier.open(json.dumps(forged).encode())
    with pytest.raises(RequestRefused, match="within"):
        verifier.check_fresh(time.time() - 120)


def test_a_daemon_refuses_overrides_by_role_and_any_file_outside_its_own(issued: Path) -> None:
    loaded = load_deployment(issued)
    daemon = HostDaemon(loaded, "laptop")
    with pytest.raises(RequestRefused, match="may not override"):
        daemon.checks.checked_overrides(("duration_s=60",), operator="alice")
    assert daemon.checks.checked_overrides(("duration_s=60",), operator="root")
    for bad in ("robot=/etc/passwd.toml", "robot=../../x", "robot=p3dx.toml", "robot=~/x"):
        with pytest.raises(RequestRefused, match="names a file"):
            daemon.checks.checked_overrides((bad,), operator="root")
    unsigned = daemon.answer("spawn", _request())
    assert b"unsigned request" in unsigned
    assert daemon.refused == 1
    assert client_identity(loaded, "operator.alice") is not None
