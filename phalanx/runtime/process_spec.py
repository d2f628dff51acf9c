"""What a fleet's process runs with, as one value: `AgentSpec` for a robot's agent (its
scenario, robot, fleet, clock, Zenoh transport, driver, telemetry).

A spec is the only way in. `phalanx agent` builds one from its options, or reads one
whole (`--spec FILE`, `-` for standard input; `--print-spec` shows what the options make);
`phalanx up` and the host daemons build one per robot and hand it to the agent they
start on its standard input (`spawn_argv`, `AgentSpec.encoded`), never as options; and
`phalanx.runtime.agent_process.run_agent` turns it into the running agent. A driver is
named as the driver registry names it, with that backend's own settings model.
"""

from __future__ import annotations

import contextlib
import difflib
import json
import subprocess
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SerializeAsAny, model_validator

from phalanx.core.config_files import validate_data
from phalanx.core.errors import ConfigError
from phalanx.core.quantities import MAX_DURATION_S, MAX_WATCHDOG_S
from phalanx.drivers import backend_names, settings_from_options, validate_settings
from phalanx.wire.bounds import UnixStamp
from phalanx.wire.transport import TransportConfig

if TYPE_CHECKING:
    from phalanx.telemetry.stream import Telemetry

SIM = "sim"  # not a backend: the world process moves a simulated robot
SPEC_ON_STDIN = "-"
MAX_SPEC_BYTES = 1 << 20  # a spec is a few kB: anything larger is refused unread


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DriverChoice(_Frozen):
    """What moves the robot: `sim` (the world process; no settings) or a backend of the
    driver registry with its settings, checked by that backend's own model.
    """

    name: str = SIM
    settings: SerializeAsAny[BaseModel] | None = None

    @model_validator(mode="before")
    @classmethod
    def _checked(cls, data: Any) -> Any:
        if not isinstance(data, Mapping):
            return data
        name, settings = data.get("name", SIM), data.get("settings")
        names = (SIM, *backend_names())
        if name not in names:
            close = difflib.get_close_matches(str(name), names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(f"driver: expected one of {', '.join(names)}, got {name!r}{hint}")
        if name == SIM:
            if settings:
                raise ConfigError("driver settings given, but the sim driver has no settings")
            return {**data, "settings": None}
        return {**data, "settings": validate_settings(name, settings or {})}


def driver_choice(
    name: str, *, options: Mapping[str, object], settings: Mapping[str, object]
) -> DriverChoice:
    """Driver `name` with its settings from backend options (`--arcos-tcp`: see
    `phalanx.drivers.settings_from_options`; None: not given) and from `settings` (the
    rest, by field name); ConfigError for a field given both ways, or any the backend's
    model refuses.
    """
    values = settings_from_options(name, options)
    for key, value in settings.items():
        if key in values:
            raise ConfigError(f"{key!r} given twice: by an option and as a driver setting")
        values[key] = value
    return DriverChoice(name=name, settings=values)


class TelemetryTarget(_Frozen):
    """Where a process's telemetry goes: an .rrd file, a live viewer (a Rerun gRPC url),
    both, or nowhere; every process of one fleet run logs under one recording id.
    """

    recording_id: str | None = None
    file: Path | None = None
    url: str | None = None

    @model_validator(mode="after")
    def _one_recording(self) -> TelemetryTarget:
        if (self.file or self.url) and self.recording_id is None:
            raise ValueError("telemetry needs --recording-id (one per fleet run)")
        return self


@contextlib.contextmanager
def telemetry_for(target: TelemetryTarget, *, robot_id: str | None) -> Iterator[Telemetry | None]:
    """The process's telemetry stream, logged from a background thread (the control loop
    comes first), closed on the way out; None when it goes nowhere.
    """
    from phalanx.telemetry.sinks import sink_for
    from phalanx.telemetry.stream import Telemetry

    sink = sink_for(target.file, target.url)
    if sink.kind == "off":
        yield None
        return
    recording = target.recording_id or ""
    with Telemetry(
        recording_id=recording, sink=sink, robot_id=robot_id, background=True
    ) as telemetry:
        yield telemetry


class AgentSpec(_Frozen):
    """Everything one robot's agent process runs with."""

    scenario: Path  # the scenario file
    overrides: tuple[str, ...] = ()  # scenario fields, `PATH=VALUE` as `--set` takes them
    robot_id: str = Field(min_length=1)
    fleet: str = Field(default="default", min_length=1)  # the Zenoh keys' phalanx/<fleet>/
    clock: Literal["lockstep", "realtime"] = "lockstep"  # simulated robots (on a driver: real)
    transport: TransportConfig = TransportConfig()
    driver: DriverChoice = DriverChoice()
    # robots on drivers: Unix time of step 0 (None: now), the wire's range of them
    epoch_s: UnixStamp | None = None
    # robots on drivers: no command this long, stop (a safety stop: never long)
    watchdog_s: float = Field(default=0.5, gt=0.0, le=MAX_WATCHDOG_S)
    camera: str | None = None  # robots on drivers: DEVICE=CALIBRATION.toml of a camera
    # simulated: no frame this long, the world is gone
    frame_timeout_s: float = Field(default=30.0, ge=0.1, le=MAX_DURATION_S)
    telemetry: TelemetryTarget = TelemetryTarget()

    def encoded(self) -> bytes:
        """The spec as JSON, as `read_spec` reads it back."""
        return self.model_dump_json().encode("utf-8")


def read_spec(path: Path, *, stdin: IO[str] | None = None) -> AgentSpec:
    """The spec in a JSON file, or on standard input for `-`; ConfigError naming the
    source and what is wrong in it.
    """
    source = "standard input" if str(path) == SPEC_ON_STDIN else str(path)
    try:
        if source == "standard input":
            text = (stdin or sys.stdin).read(MAX_SPEC_BYTES + 1)
        else:
            with path.open(encoding="utf-8") as src:
                text = src.read(MAX_SPEC_BYTES + 1)
        if len(text) > MAX_SPEC_BYTES:
            raise ConfigError(f"agent spec {source}: over {MAX_SPEC_BYTES} bytes")
        data = json.loads(text)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"agent spec {source}: cannot read it as JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"agent spec {source}: expected a JSON object")
    return validate_data(AgentSpec, data, source=f"agent spec {source}")


def spawn_argv(spec: AgentSpec, *, python: str) -> list[str]:
    """The command line of an agent started with `spec` on its standard input. The spec
    says everything; its robot and fleet are repeated (and checked against it) so that a
    list of processes tells the agents apart.
    """
    return [
        *(python, "-m", "phalanx", "agent"),
        *("--robot", spec.robot_id, "--fleet", spec.fleet, "--spec", SPEC_ON_STDIN),
    ]


def hand_spec(process: subprocess.Popen[bytes], spec: AgentSpec) -> None:
    """Write `spec` to the standard input of an agent just started with `spawn_argv`
    (and `stdin=PIPE`), and close it; an agent that died at once is left to its
    supervisor, which sees it exit.
    """
    if process.stdin is None:
        raise ValueError("the agent was started without a pipe to its standard input")
    with contextlib.suppress(BrokenPipeError), process.stdin:
        process.stdin.write(spec.encoded())
