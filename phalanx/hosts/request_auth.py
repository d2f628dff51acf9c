"""Who sent a request to a host daemon: an operator's signature on every spawn and stop.

Zenoh's access control decides what reaches a daemon by the certificate of the link it
came over, which for a request forwarded by another host is that host's. So a secured
deployment's launcher also signs each request with its operator key: the envelope
carries the request's bytes, the operator's certificate and an ECDSA signature over
those bytes. The daemon checks, on every request: the certificate was issued by the
fleet's CA and is valid now; its common name is `operator.<name>` with the name in the
deployment's `[security] operators`; the signature; the request's `issued_unix` within
`request_window_s` of the daemon's clock; and that the same signature was not seen before
(a replayed request). Each failure is a `RequestRefused` naming it.
"""

from __future__ import annotations

import base64
import time
from collections import OrderedDict
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from phalanx.core.errors import ConfigError, RequestRefused
from phalanx.hosts.pki import role_of, verify_chain
from phalanx.wire.security import TlsFiles

MAX_CERT_BYTES = 8192
MAX_SEEN = 4096


class SignedRequest(BaseModel):
    """A request's bytes, with the operator's certificate and signature over them."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    request: str = Field(max_length=65536)  # base64 of the request's JSON
    cert: str = Field(max_length=MAX_CERT_BYTES)  # PEM
    signature: str = Field(max_length=512)  # base64 of the DER ECDSA-SHA256 signature


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


class RequestVerifier:
    """A daemon's check of who signed a request (and that it is fresh and new)."""

    def __init__(self, ca: Path, operators: tuple[str, ...], window_s: float) -> None:
        self.ca, self.operators, self.window_s = ca, operators, window_s
        self._seen: OrderedDict[str, float] = OrderedDict()

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
        self._check_new(envelope.signature)
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

    def _check_new(self, signature: str) -> None:
        now = time.monotonic()
        while self._seen and next(iter(self._seen.values())) < now - 2 * self.window_s:
            self._seen.popitem(last=False)
        if signature in self._seen:
            raise RequestRefused("request already served (a replay)")
        self._seen[signature] = now
        while len(self._seen) > MAX_SEEN:
            self._seen.popitem(last=False)

    def check_fresh(self, issued_unix: float | None) -> None:
        """The request was issued within the window of this host's clock."""
        if issued_unix is None or abs(time.time() - issued_unix) > self.window_s:
            raise RequestRefused(
                f"request issued at {issued_unix}: not within {self.window_s:.0f} s of this "
                "host's clock (a replay, or unsynced clocks)"
            )
