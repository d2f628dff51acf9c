"""How the `arcos` driver reaches its robot and how it treats the link (a pydantic model:
the driver registry checks `--driver-setting` values and deployment files against it).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

from phalanx.core.quantities import Angle

PLACE_MAX_M = 10_000.0  # a simulated robot is put no further out than this (m)
_Place = Annotated[float, Field(ge=-PLACE_MAX_M, le=PLACE_MAX_M)]


def _is_tcp(address: str) -> bool:
    host, sep, port = address.rpartition(":")
    return bool(sep and host and port.isdigit()) and not address.startswith("/")


class ArcosSettings(BaseModel):
    """How to reach the robot. Exactly one of `port` (serial device) or `tcp` (host:port);
    `fallbacks`: other addresses of the same robot, tried in turn when it must reconnect.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    port: str | None = None
    tcp: str | None = None
    fallbacks: tuple[str, ...] = Field(
        default=(), description="e.g. /dev/ttyUSB1 (an adapter re-plugged), host:8102"
    )
    baud: int = Field(
        default=9600, ge=300, le=4_000_000, description="9600 at power-up; 19200-115200 if set"
    )
    connect_timeout_s: float = Field(default=5.0, gt=0.0, le=3600.0)
    sync_retries: int = Field(default=5, ge=1, le=1000)
    config_timeout_s: float = Field(default=1.0, gt=0.0, le=60.0, description="ARIA waits 1 s")
    pulse_s: float = Field(
        default=0.5, gt=0.0, le=10.0, description="keep-alive period (ARIA: 0.5)"
    )
    link_timeout_s: float = Field(
        default=1.0, gt=0.0, le=60.0, description="no SIP this long = lost"
    )
    reconnect: bool = True
    reconnect_backoff_max_s: float = Field(default=2.0, gt=0.0, le=3600.0)
    sonar: bool = True
    adopt_accelerations: bool = Field(
        default=True, description="raise the robot's (de)accelerations to the robot file's"
    )
    # A simulator (AMRISim, MobileSim: its CONFIG packet's serial number is "SIM").
    place_at: tuple[_Place, _Place, Angle] | None = Field(
        default=None,
        description="simulators only: (x m, y m, heading deg) in the simulator's frame, "
        "where the robot is put (SIM_SET_POSE) when first connected",
    )
    simstat: bool | None = Field(
        default=None,
        description="ask for the robot's true pose (SIM_STAT); default: from a simulator",
    )
    heading_step_deg: float | None = Field(
        default=None,
        gt=0.0,
        le=10.0,
        description="the robot reports its heading in steps this coarse, followed finer "
        "from its yaw rate; default: 1 for a simulator (whole degrees), else none",
    )

    @model_validator(mode="after")
    def _one_link(self) -> ArcosSettings:
        if (self.port is None) == (self.tcp is None):
            raise ValueError("give exactly one of port (serial device) or tcp (host:port)")
        for address in (self.tcp,) if self.tcp is not None else ():
            if not _is_tcp(address):
                raise ValueError(f"tcp must be host:port, got {address!r}")
        for address in self.fallbacks:
            if not (address.startswith("/") or _is_tcp(address)):
                raise ValueError(f"a fallback is a serial device or host:port, got {address!r}")
        return self

    @property
    def address(self) -> str:
        """The serial device or host:port, for messages."""
        return self.port or self.tcp or "?"

    @property
    def addresses(self) -> tuple[tuple[str, bool], ...]:
        """Every address to try, in order, each with whether it is TCP."""
        return tuple((a, _is_tcp(a)) for a in (self.address, *self.fallbacks))
