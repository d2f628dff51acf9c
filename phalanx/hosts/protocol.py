"""The host daemon's protocol: keys, requests, replies and log lines (JSON over Zenoh).

Keys, under the fleet's prefix:
    phalanx/<fleet>/host/<name>/alive        liveliness token of the daemon
    phalanx/<fleet>/host/<name>/spawn        queryable: SpawnRequest -> HostReply
    phalanx/<fleet>/host/<name>/stop         queryable: StopRequest -> HostReply
    phalanx/<fleet>/host/<name>/status       queryable: (no payload) -> HostReply
    phalanx/<fleet>/host/<name>/log/<child>  LogLine, every line a child prints

A request names a deployment by name and digest; it never carries a command, a path or
a driver setting: the daemon builds every command line from its own copy of the
deployment. Everything in a request is checked by these models (unknown fields, wrong
version, bad names, non-finite numbers are refused) and then against the deployment.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from phalanx.hosts.deployment import NAME_PATTERN
from phalanx.wire.bounds import Count

PROTOCOL_VERSION: Literal[1] = 1
MAX_REQUEST_BYTES = 64 * 1024
RUN_ID_PATTERN = r"^[A-Za-z0-9_-]{1,40}$"
# PATH=VALUE, printable; the value is parsed as TOML and the scenario validated again.
OVERRIDE_PATTERN = r"^[A-Za-z_][A-Za-z0-9_.]{0,80}=[^\x00-\x1f\x7f]{0,200}$"
MAX_LOG_LINE = 2000

Name = Annotated[str, Field(pattern=NAME_PATTERN)]
RunId = Annotated[str, Field(pattern=RUN_ID_PATTERN)]
Override = Annotated[str, Field(pattern=OVERRIDE_PATTERN)]
Digest = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
ChildState = Literal[
    "starting",  # spawned, not on the fabric yet
    "running",  # its liveliness token is up
    "backoff",  # crashed, restarting after a delay
    "finished",  # ended by itself with exit code 0
    "stopping",  # asked to stop (SIGTERM sent; SIGKILL after the grace period)
    "stopped",  # ended after being asked to
    "failed",  # crashed, and out of restarts (or the world crashed)
]
ACTIVE_STATES: frozenset[str] = frozenset({"starting", "running", "backoff", "stopping"})


class Wire(BaseModel):
    """Base of the protocol's messages: frozen, unknown fields and NaN/inf refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SpawnRequest(Wire):
    """Start this run's processes on a host: its agents (all, or some) and the world."""

    version: Literal[1] = PROTOCOL_VERSION
    deployment: Name
    digest: Digest  # of the launcher's deployment and scenario files: must match the host's
    run_id: RunId
    robots: tuple[Name, ...] = Field(default=(), max_length=256)  # empty: all of this host's
    world: bool = True  # start the world too, if it runs on this host
    epoch_unix: float | None = None  # step 0 of robots on real drivers (Unix time)
    overrides: tuple[Override, ...] = Field(default=(), max_length=32)
    issued_unix: float | None = None  # when the launcher sent it (a secured fleet's window)


class StopRequest(Wire):
    """Stop processes on a host: all of them, or some robots (and/or the world). Like a
    spawn, it carries the digest of the deployment's files: only a launcher holding
    them (`phalanx launch`, `phalanx stop`) can end a fleet's processes.
    """

    version: Literal[1] = PROTOCOL_VERSION
    deployment: Name
    digest: Digest
    run_id: RunId | None = None  # only if this run is the host's current one
    robots: tuple[Name, ...] = Field(default=(), max_length=256)  # empty: all
    world: bool = True
    issued_unix: float | None = None  # when the launcher sent it (a secured fleet's window)


class ChildStatus(Wire):
    """One supervised process on a host."""

    name: str
    kind: Literal["agent", "world"]
    state: ChildState
    pid: Count | None = None
    restarts: Count = 0
    # times it ended on its own with an error (finished runs exit 0)
    crashes: Count = 0
    exit_code: int | None = Field(default=None, ge=-256, le=255)  # (negative: its signal)
    last_error: str = ""
    log_dropped: Count = 0


class HostStatus(Wire):
    """What a host daemon runs, and its counters."""

    version: Literal[1] = PROTOCOL_VERSION
    host: str
    fleet: str
    deployment: str
    digest: str
    time_unix: float  # the host's clock, for the launcher's skew check
    uptime_s: float
    run_id: str | None = None
    robots: tuple[str, ...] = ()  # assigned to this host
    world: bool = False  # the world runs here
    children: tuple[ChildStatus, ...] = ()
    requests: int = 0
    refused: int = 0  # every request refused, for any reason
    replays: int = 0  # of those, requests served before (a secured fleet's replay record)


class HostReply(Wire):
    """The answer to every request: accepted or refused (with why), and the host's status."""

    version: Literal[1] = PROTOCOL_VERSION
    ok: bool
    error: str = ""
    status: HostStatus


class LogLine(Wire):
    """A line a child printed (stdout and stderr, merged)."""

    version: Literal[1] = PROTOCOL_VERSION
    host: str
    child: str
    run_id: str
    time_unix: float
    level: Literal["info", "warning", "error"] = "info"
    line: str = Field(max_length=MAX_LOG_LINE)


def line_level(line: str) -> Literal["info", "warning", "error"]:
    """How serious a log line looks (Python logging's level names, tracebacks)."""
    if any(m in line for m in (" ERROR ", " CRITICAL ", "Traceback", "Error:", "Exception")):
        return "error"
    if " WARNING " in line:
        return "warning"
    return "info"
