"""What a host daemon accepts in a request, checked before anything starts or stops.

A request must name the host's own deployment (and, to spawn, carry the digest of the
same deployment and scenario files), robots of the deployment that run on this host,
scenario overrides only where the deployment allows them (and valid ones), and an epoch
within a day of the host's clock. Every check raises `RequestRefused` with the reason.
"""

from __future__ import annotations

import re
import time

from pydantic import ValidationError

from phalanx.core.config_files import apply_overrides
from phalanx.core.errors import RequestRefused
from phalanx.hosts.deployment import LoadedDeployment, did_you_mean

MAX_EPOCH_OFFSET_S = 86_400.0


def validation_summary(exc: ValidationError, limit: int = 4) -> str:
    """`field: message; ...` for the first few errors of `exc`."""
    parts = []
    for error in exc.errors()[:limit]:
        path = ".".join(str(p) for p in error["loc"]) or "<payload>"
        parts.append(f"{path}: {error['msg']}")
    return "; ".join(parts)


class RequestChecks:
    """The checks of one host of a deployment on what a request names."""

    def __init__(self, loaded: LoadedDeployment, host: str) -> None:
        self.loaded, self.host = loaded, host
        self.spec = loaded.spec

    def check_deployment(self, name: str, digest: str | None = None) -> None:
        """The request names this host's deployment (and, given a digest, the same files)."""
        if name != self.spec.name:
            raise RequestRefused(
                f"host {self.host!r} serves deployment {self.spec.name!r}, not {name!r}"
            )
        if digest is not None and digest != self.loaded.digest:
            raise RequestRefused(
                f"deployment {name!r} differs on host {self.host!r} (digest "
                f"{self.loaded.digest[:12]} here, {digest[:12]} asked): copy the same deployment "
                "and scenario files to every host"
            )

    def requested_robots(self, requested: tuple[str, ...]) -> tuple[str, ...]:
        """The robots asked for, all of the deployment and on this host; none: every one here."""
        here = self.spec.robots_on(self.host)
        everyone = [r.id for r in self.spec.robots]
        for rid in requested:
            if rid not in everyone:
                raise RequestRefused(
                    f"robot {rid!r} is not in deployment {self.spec.name!r}"
                    + did_you_mean(rid, everyone)
                )
            if rid not in here:
                other = self.spec.placement(rid).host
                raise RequestRefused(f"robot {rid!r} runs on host {other!r}, not on {self.host!r}")
        return requested or here

    def checked_overrides(
        self, overrides: tuple[str, ...], *, operator: str | None = None
    ) -> tuple[str, ...]:
        """The overrides, if the deployment allows them, the requesting operator may give
        them (a secured fleet: `[security] may_override`), none names a file, and they
        give a valid scenario.
        """
        if not overrides:
            return ()
        if not self.spec.allow_overrides:
            raise RequestRefused(
                f"deployment {self.spec.name!r} does not allow overrides (allow_overrides = false)"
            )
        if self.spec.secured:
            allowed = self.spec.security.may_override if self.spec.security else ()
            if operator not in allowed:
                raise RequestRefused(
                    f"operator {operator!r} may not override the scenario "
                    f"([security] may_override: {', '.join(allowed) or 'nobody'})"
                )
        for override in overrides:
            _no_file(override)
        apply_overrides(  # ConfigError if invalid
            self.loaded.scenario, list(overrides), source=str(self.loaded.scenario_path)
        )
        return overrides

    @staticmethod
    def check_epoch(epoch_unix: float | None) -> None:
        """The run's epoch, if any, is within a day of this host's clock."""
        if epoch_unix is not None and abs(epoch_unix - time.time()) > MAX_EPOCH_OFFSET_S:
            raise RequestRefused(f"epoch {epoch_unix:.3f}: more than a day from this host's clock")


_PATHLIKE = re.compile(r"[/\\~]|\.\.|\.(toml|json|yaml|yml|rrd|py)\b", re.IGNORECASE)


def _no_file(override: str) -> None:
    """Refuse an override whose value names a file: a daemon reads only the deployment's own
    files (`robot=/etc/passwd.toml` would make it open any file its user can read).
    """
    value = override.partition("=")[2]
    if _PATHLIKE.search(value):
        raise RequestRefused(
            f"override {override!r} names a file: a host reads only its deployment's own files "
            "(put the file beside the scenario and name it there)"
        )
