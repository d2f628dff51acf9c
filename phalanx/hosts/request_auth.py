"""Who sent a request to a host daemon: an operator's signature on every spawn and stop.

Zenoh's access control decides what reaches a daemon by the certificate of the link it
came over, which for a request forwarded by another host is that host's. So a secured
deployment's launcher also signs each request with its operator key: the envelope
carries the request's bytes, the operator's certificate and an ECDSA signature over
those bytes. The daemon checks, on every request: the certificate was issued by the
fleet's CA and is valid now; its common name is `operator.<name>` with the name in the
deployment's `[security] operators`; the signature; the request's `issued_unix` within
`request_window_s` of the daemon's clock; and that the same request was not served before
(a replay). Each failure is a `RequestRefused` naming it.

Served requests are known by the SHA-256 of their bytes (an ECDSA signature is not
unique: `(r, n - s)` verifies as well as `(r, s)`), and remembered in the daemon's state
folder (`ServedRequests`) until they are past the window, so that a request captured on
the network is refused after the daemon restarts too. If that record cannot be read, the
daemon refuses every request issued before it started, until they are past the window.
"""

from __future__ import annotations

import base64
import hashlib
import logging
import os
import stat
import time
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from phalanx.core.errors import ConfigError, RequestRefused
from phalanx.core.files import write_private
from phalanx.hosts.pki import role_of, verify_chain
from phalanx.wire.security import TlsFiles

log = logging.getLogger("phalanx.host")
MAX_CERT_BYTES = 8192
# Requests remembered at once: an operator would have to send this many within two
# windows; past it a request is refused (never a served one forgotten early).
MAX_SEEN = 4096
SERVED_FILE = "served-requests.json"
MAX_SERVED_BYTES = MAX_SEEN * 100 + 1024  # a record is under 100 bytes of JSON

RequestId = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
UnixTime = Annotated[float, Field(ge=0.0, le=2.0**33)]


class SignedRequest(BaseModel):
    """A request's bytes, with the operator's certificate and signature over them."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    request: str = Field(max_length=65536)  # base64 of the request's JSON
    cert: str = Field(max_length=MAX_CERT_BYTES)  # PEM
    signature: str = Field(max_length=512)  # base64 of the DER ECDSA-SHA256 signature


class ServedRecord(BaseModel):
    """The state file: each served request's id and when it may be forgotten (Unix s)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    version: Literal[1] = 1
    served: tuple[tuple[RequestId, UnixTime], ...] = Field(default=(), max_length=MAX_SEEN)


def sign(request: bytes, files: TlsFiles) -> bytes:
    """`request` wrapped and signed with the key of `files` (its certificate included)."""
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    key = serialization.load_pem_private_key(Path(files.key).read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ConfigError(f"{files.key}: not an ECDSA key issued by `phalanx pki`")
    signature = key.sign(request, ec.ECDSA(hashes.SHA256()))
    envelope = SignedRequest(
        request=base64.b64encode(request).decode("ascii"),
        cert=Path(files.cert).read_text(),
        signature=base64.b64encode(signature).decode("ascii"),
    )
    return envelope.model_dump_json().encode("utf-8")


def request_id(request: bytes) -> str:
    """What a served request is remembered by: the SHA-256 of its bytes (hex)."""
    return hashlib.sha256(request).hexdigest()


class ServedRequests:
    """The requests a daemon served and may not serve again: in memory, and (given a
    folder) in its `served-requests.json`, rewritten whole (a temporary file renamed over
    it, mode 0600) on every request served. Bounded: an entry goes once it is past the
    window (`expiry` in Unix time), and at MAX_SEEN a new request is refused.
    """

    def __init__(self, folder: Path | None) -> None:
        self.path = folder / SERVED_FILE if folder is not None else None
        self.readable = True  # False: the file was there but could not be trusted
        self.write_errors = 0
        self._expiry: dict[str, float] = {}
        if self.path is not None:
            self._load(self.path)

    def _load(self, path: Path) -> None:
        try:
            record = _read_record(path)
        except FileNotFoundError:
            return
        except (OSError, ValueError) as exc:  # ValidationError is a ValueError
            self.readable = False
            log.error("%s cannot be trusted (%s): refusing requests issued before now", path, exc)
            return
        self._expiry = dict(record.served)

    def holds(self, rid: str, *, now_unix: float) -> bool:
        """Whether `rid` was served and is not past its window yet."""
        self._forget(now_unix)
        return rid in self._expiry

    def add(self, rid: str, *, expiry_unix: float, now_unix: float) -> None:
        """Remember `rid` until `expiry_unix`, and write the record of those not past
        their window at `now_unix` (RequestRefused if MAX_SEEN are held).
        """
        self._forget(now_unix)
        if len(self._expiry) >= MAX_SEEN:
            raise RequestRefused(
                f"{MAX_SEEN} requests served within the request window: try again later"
            )
        self._expiry[rid] = expiry_unix
        self._save()

    def _forget(self, now_unix: float) -> None:
        self._expiry = {r: t for r, t in self._expiry.items() if t >= now_unix}

    def _save(self) -> None:
        """Write the record (a failure is logged and counted: the request is still served,
        protected against replay until this daemon restarts, as it would be without a file:
        a full disk must not keep an operator from stopping the fleet).
        """
        if self.path is None:
            return
        record = ServedRecord(served=tuple(self._expiry.items()))
        try:
            write_private(self.path, record.model_dump_json().encode("utf-8"))
        except OSError as exc:
            self.write_errors += 1
            log.error("cannot record a served request in %s: %s", self.path, exc)


def _read_record(path: Path) -> ServedRecord:
    """The record in `path`, if it is this user's own, private and of bounded size."""
    with path.open("rb") as src:
        info = os.fstat(src.fileno())
        if info.st_uid != os.geteuid() or info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise ValueError("not a private file of this user (mode 0600 expected)")
        data = src.read(MAX_SERVED_BYTES + 1)
    if len(data) > MAX_SERVED_BYTES:
        raise ValueError(f"over {MAX_SERVED_BYTES} bytes")
    return ServedRecord.model_validate_json(data)


class RequestVerifier:
    """A daemon's check of who signed a request (and that it is fresh and new).

    `state`: the folder where served requests are remembered across restarts (None: in
    memory only).
    """

    def __init__(
        self, ca: Path, operators: tuple[str, ...], window_s: float, *, state: Path | None = None
    ) -> None:
        self.ca, self.operators, self.window_s = ca, operators, window_s
        self.served = ServedRequests(state)
        self.replays = 0  # requests refused as served before
        self.started_unix = time.time()

    def open(self, payload: bytes) -> tuple[str, bytes]:
        """The operator's name and the request's bytes; RequestRefused saying why not."""
        try:
            envelope = SignedRequest.model_validate_json(payload)
            request = base64.b64decode(envelope.request, validate=True)
            signature = base64.b64decode(envelope.signature, validate=True)
        except (ValidationError, ValueError) as exc:
            raise RequestRefused(
                "unsigned request: this fleet is secured; requests must be signed by an "
                "operator's certificate (phalanx launch --identity operator.NAME)"
            ) from exc
        try:
            cn = verify_chain(envelope.cert.encode("utf-8"), self.ca)
        except ConfigError as exc:
            raise RequestRefused(f"request signed by a certificate refused: {exc}") from exc
        name = cn.split(".", 1)[-1]
        if role_of(cn) != "operator" or name not in self.operators:
            raise RequestRefused(
                f"{cn!r} may not start or stop this fleet (operators: "
                f"{', '.join(self.operators) or 'none'})"
            )
        self._check_signature(envelope.cert.encode("utf-8"), request, signature)
        self._check_new(request)
        return name, request

    @staticmethod
    def _check_signature(cert_pem: bytes, request: bytes, signature: bytes) -> None:
        from cryptography import x509
        from cryptography.exceptions import InvalidSignature
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec

        public = x509.load_pem_x509_certificate(cert_pem).public_key()
        try:
            if not isinstance(public, ec.EllipticCurvePublicKey):
                raise InvalidSignature
            public.verify(signature, request, ec.ECDSA(hashes.SHA256()))
        except InvalidSignature as exc:
            raise RequestRefused("request signature does not match its certificate") from exc

    def _check_new(self, request: bytes) -> None:
        """Refuse a request served before (counted); remember this one while it could
        still pass `check_fresh` (issued at most a window ahead of now: two windows).
        """
        now, rid = time.time(), request_id(request)
        if self.served.holds(rid, now_unix=now):
            self.replays += 1
            raise RequestRefused("request already served (a replay)")
        self.served.add(rid, expiry_unix=now + 2 * self.window_s, now_unix=now)

    def check_fresh(self, issued_unix: float | None) -> None:
        """The request was issued within the window of this host's clock (and, if the
        record of served requests could not be read, after this daemon started).
        """
        if issued_unix is None or abs(time.time() - issued_unix) > self.window_s:
            raise RequestRefused(
                f"request issued at {issued_unix}: not within {self.window_s:.0f} s of this "
                "host's clock (a replay, or unsynced clocks)"
            )
        if not self.served.readable and issued_unix < self.started_unix:
            raise RequestRefused(
                f"request issued at {issued_unix:.3f}, before this daemon started, and its "
                f"record of served requests ({self.served.path}) could not be read: send it "
                "again"
            )
