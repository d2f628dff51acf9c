"""Zenoh's TLS links and access control, as phalanx configures them.

`TlsFiles` is one process's identity on `tls/` endpoints: the fleet's CA, its own
certificate and key, with mutual authentication (a listener refuses a peer without a
certificate of the same CA, a connector checks the listener's certificate names the
address it dialled). `AccessControl` is Zenoh's access-control list (rules, subjects
matched by certificate common names, policies joining them), default deny; it is built
from a deployment in `phalanx.hosts.access`, never written by hand.

Zenoh 1.x facts this relies on: TLS settings live under `transport/link/tls`
(`root_ca_certificate`, `listen_certificate`, `listen_private_key`,
`connect_certificate`, `connect_private_key`, `enable_mtls`); a listener with
`enable_mtls` refuses a client without a certificate its CA signed, or an expired one;
with `access_control` enabled and `default_permission = "deny"`, a message of a kind and
key no rule of the sender's subject allows is dropped at the router (a put, a
liveliness token, a query), in each direction (`ingress` into the router, `egress` out
of it) separately.
"""

from __future__ import annotations

import json
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

MessageKind = Literal[
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]
Flow = Literal["ingress", "egress"]
READS: tuple[MessageKind, ...] = (
    "declare_subscriber",
    "declare_liveliness_subscriber",
    "liveliness_query",
)


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TlsFiles(_Frozen):
    """One process's TLS identity: PEM paths (the CA's certificate, its own and its key)."""

    ca: str
    cert: str
    key: str
    mtls: bool = True


class AclRule(_Frozen):
    """Allow `messages` on `key_exprs` in `flows`."""

    id: str
    messages: tuple[MessageKind, ...]
    flows: tuple[Flow, ...] = ("ingress",)
    key_exprs: tuple[str, ...] = Field(min_length=1)
    permission: Literal["allow", "deny"] = "allow"


class AclPolicy(_Frozen):
    """The rules that apply to the peers whose certificate's common name is in `names`."""

    id: str
    names: tuple[str, ...] = Field(min_length=1)
    rules: tuple[AclRule, ...] = Field(min_length=1)


class AccessControl(_Frozen):
    """A default-deny access-control list of one router, as policies per common name."""

    policies: tuple[AclPolicy, ...] = ()
    default_permission: Literal["allow", "deny"] = "deny"

    def zenoh_json(self) -> dict[str, Any]:
        """The `access_control` section of a Zenoh configuration."""
        rules: dict[str, AclRule] = {}
        subjects, policies = [], []
        for policy in self.policies:
            for rule in policy.rules:
                rules[rule.id] = rule
            subjects.append({"id": f"s-{policy.id}", "cert_common_names": list(policy.names)})
            policies.append(
                {
                    "id": policy.id,
                    "rules": [r.id for r in policy.rules],
                    "subjects": [f"s-{policy.id}"],
                }
            )
        return {
            "enabled": True,
            "default_permission": self.default_permission,
            "rules": [
                {
                    "id": r.id,
                    "messages": list(r.messages),
                    "flows": list(r.flows),
                    "permission": r.permission,
                    "key_exprs": list(r.key_exprs),
                }
                for r in rules.values()
            ],
            "subjects": subjects,
            "policies": policies,
        }

    def describe(self) -> str:
        """The rules as text, one line each (`phalanx launch --print-acl`)."""
        lines = [f"default: {self.default_permission}"]
        for policy in self.policies:
            lines.append(f"{', '.join(policy.names)}:")
            for rule in policy.rules:
                lines.append(
                    f"  {rule.permission} {'+'.join(rule.flows)} {', '.join(rule.messages)}"
                    f" on {', '.join(rule.key_exprs)}"
                )
        return "\n".join(lines)


def tls_section(files: TlsFiles) -> dict[str, Any]:
    """The `transport/link/tls` section for `files` (the same identity listens and connects)."""
    return {
        "root_ca_certificate": files.ca,
        "listen_certificate": files.cert,
        "listen_private_key": files.key,
        "connect_certificate": files.cert,
        "connect_private_key": files.key,
        "enable_mtls": files.mtls,
        "verify_name_on_connect": True,
    }


def apply_security(conf: Any, tls: TlsFiles | None, acl: AccessControl | None) -> None:
    """Insert the TLS identity and the access-control list into a zenoh.Config."""
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(tls_section(tls)))
    if acl is not None:
        conf.insert_json5("access_control", json.dumps(acl.zenoh_json()))
