"""A signed request captured on the network and sent again after the host daemon
restarted (row 3 of the security issue): refused, and counted, by a real daemon process.

The daemon (`phalanx host`, a secured deployment of one loopback host) serves a signed
stop request; it is then killed (SIGKILL: nothing written on the way out) and started
again with the same state folder, and the very same bytes are sent within the request
window, and once more with the other ECDSA signature of the same request, `(r, n - s)`.
"""

from __future__ import annotations

import base64
import json
import os
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from phalanx.core.config_files import CONFIG_ROOT
from phalanx.hosts import pki
from phalanx.hosts.access import identities, identity_files
from phalanx.hosts.deployment import LoadedDeployment, load_deployment
from phalanx.hosts.fleet_client import FleetClient
from phalanx.hosts.protocol import HostReply, StopRequest
from phalanx.hosts.request_auth import SERVED_FILE, sign
from phalanx.hosts.wiring import client_transport
from phalanx.wire.transport import free_tcp_port

pytestmark = pytest.mark.integration
CLI = [sys.executable, "-m", "phalanx"]
HOST = "laptop"
WAIT_S = 30.0
# The order of the P-256 group: (r, s) and (r, n - s) are both valid signatures.
P256_N = 0xFFFFFFFF00000000FFFFFFFFFFFFFFFFBCE6FAADA7179E84F3B9CAC2FC632551


@dataclass
class Daemon:
    """One `phalanx host` process of the deployment, its state folder kept across starts."""

    loaded: LoadedDeployment
    state_home: Path
    log: Path
    proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        """Start the daemon (its log appended to)."""
        argv = [*CLI, "host", str(self.loaded.path), "--name", HOST]
        env = {**os.environ, "XDG_STATE_HOME": str(self.state_home)}
        env.pop("STATE_DIRECTORY", None)
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env)

    def kill(self) -> None:
        """SIGKILL, and reap it."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> int | None:
        """SIGTERM (SIGKILL after 20 s); its exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                return self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        return self.proc.wait(5)


def _deployment(folder: Path) -> LoadedDeployment:
    lines = [
        'name = "replay"', 'fleet = "replay"',
        f'scenario = "{CONFIG_ROOT / "scenarios" / "paper_wedge.toml"}"', 'clock = "realtime"',
        "[security]", 'mode = "mtls"', 'operators = ["alice"]', "request_window_s = 60",
        "[zenoh]", "lease_ms = 500", "retry_max_ms = 250",
        "[world]", f'host = "{HOST}"', f'out_dir = "{folder / "results"}"', "recording = false",
        "[[hosts]]", f'name = "{HOST}"', 'address = "127.0.0.1"', f"port = {free_tcp_port()}",
    ]  # fmt: skip
    for rid in ("r1", "r2", "r3"):
        lines += ["[[robots]]", f'id = "{rid}"', f'host = "{HOST}"']
    path = folder / "replay.toml"
    path.write_text("\n".join(lines) + "\n")
    loaded = load_deployment(path)
    pki.init_ca(folder / "pki", fleet=loaded.spec.fleet)
    for ident in identities(loaded.spec):
        pki.issue(folder / "pki", ident.common_name, addresses=ident.addresses)
    return loaded


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[Daemon]:
    """The secured deployment's daemon, started; stopped at the end."""
    made = Daemon(_deployment(tmp_path), tmp_path / "state", tmp_path / "host.log")
    made.start()
    try:
        yield made
    finally:
        code = made.stop()
        assert code in (0, None), made.log.read_text(errors="replace")[-3000:]


def _ask(loaded: LoadedDeployment, payload: bytes) -> HostReply:
    tls = identity_files(loaded, "operator.alice")
    with FleetClient(loaded, client_transport(loaded.spec, via=HOST, tls=tls)) as client:
        client.wait_for_hosts(WAIT_S, lambda _text: None)
        reply = client.ask("stop", {HOST: payload}, timeout_s=10.0)[HOST]
    assert reply is not None, "the daemon did not answer"
    return reply


def _other_signature(payload: bytes) -> bytes:
    """The same signed request with its signature's s replaced by n - s (still valid)."""
    from cryptography.hazmat.primitives.asymmetric.utils import (
        decode_dss_signature,
        encode_dss_signature,
    )

    envelope = json.loads(payload)
    r, s = decode_dss_signature(base64.b64decode(envelope["signature"]))
    twin = encode_dss_signature(r, P256_N - s)
    envelope["signature"] = base64.b64encode(twin).decode("ascii")
    return json.dumps(envelope).encode("utf-8")


def test_a_signed_request_is_refused_after_the_daemon_restarts(daemon: Daemon) -> None:
    loaded = daemon.loaded
    request = StopRequest(deployment=loaded.spec.name, digest=loaded.digest,
                          issued_unix=time.time())  # fmt: skip
    captured = sign(request.model_dump_json().encode(), identity_files(loaded, "operator.alice"))
    first = _ask(loaded, captured)
    assert first.ok, first.error

    daemon.kill()  # no chance to write anything on the way out
    daemon.start()
    replayed = _ask(loaded, captured)
    twin = _ask(loaded, _other_signature(captured))

    assert not replayed.ok
    assert "already served" in replayed.error, replayed.error
    assert not twin.ok
    assert "already served" in twin.error, twin.error
    assert twin.status.replays == 2  # both counted, as refusals too
    assert twin.status.refused == 2
    record = daemon.state_home / "phalanx" / loaded.spec.fleet / HOST / SERVED_FILE
    assert stat.S_IMODE(record.stat().st_mode) == 0o600
    assert len(json.loads(record.read_text())["served"]) == 1  # only what is in the window
    fresh = StopRequest(deployment=loaded.spec.name, digest=loaded.digest,
                        issued_unix=time.time())  # fmt: skip
    again = _ask(loaded, sign(fresh.model_dump_json().encode(),
                              identity_files(loaded, "operator.alice")))  # fmt: skip
    assert again.ok, again.error  # a new request is served as before


def test_an_untrusted_record_refuses_what_was_issued_before_the_start(tmp_path: Path) -> None:
    """A record another user could have written (mode 0644), or garbage: not read, and
    every request issued before the daemon started is refused (until past the window).
    """
    from phalanx.core.errors import RequestRefused
    from phalanx.hosts.request_auth import RequestVerifier, ServedRequests, request_id

    record = tmp_path / SERVED_FILE
    kept = ServedRequests(tmp_path)
    now = time.time()
    kept.add(request_id(b"old"), expiry_unix=now + 1.0, now_unix=now)
    kept.add(request_id(b"new"), expiry_unix=now + 60.0, now_unix=now)
    assert ServedRequests(tmp_path).holds(request_id(b"new"), now_unix=now)
    kept.add(request_id(b"newer"), expiry_unix=now + 60.0, now_unix=now + 2.0)  # "old" is past
    assert len(json.loads(record.read_text())["served"]) == 2  # the expired one forgotten
    for spoil in ("0644", "garbage"):
        if spoil == "0644":
            record.chmod(0o644)
        else:
            record.write_text('{"version": 1, "served": [["zz", 1e300]]}')
            record.chmod(0o600)
        issued = time.time()
        verifier = RequestVerifier(tmp_path / "ca.crt", ("alice",), 30.0, state=tmp_path)
        assert not verifier.served.readable
        with pytest.raises(RequestRefused, match="before this daemon started"):
            verifier.check_fresh(issued)
        verifier.check_fresh(time.time() + 1.0)  # issued since: served
