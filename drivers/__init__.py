"""Robot drivers: the `Driver` protocol, shared safety, and the backends, chosen by name.

`BACKENDS` says where each backend's driver and settings classes live. A backend's module,
and with it its hardware library (pyserial, python-can, canopen), is imported only when
that backend is asked for: importing `phalanx.drivers` imports none of them. Each backend
declares its settings once, as its own pydantic model, and every backend class is built
the same way, `Driver(settings, *, robot=robot_params)`. A backend may also name the
`phalanx agent` options that each set one of its settings (`--arcos-tcp`: `tcp`), read by
`settings_from_options`:

    driver = open_driver("arcos", {"port": "/dev/ttyUSB0"}, robot=load_robot("p3dx"))

`sim` is not a backend: in a fleet the world process moves a simulated robot and there is
no driver object; `phalanx.drivers.sim.SimDriver` is that robot behind the Driver protocol,
for the conformance suite and tools.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

from pydantic import BaseModel

from phalanx.core.config_files import validate_data
from phalanx.core.errors import ConfigError, DriverUnavailable

if TYPE_CHECKING:
    from phalanx.core.robot_params import RobotParams
    from phalanx.drivers.base import Driver


@dataclass(frozen=True)
class Backend:
    """Where a backend lives (imported on first use), what it is in one line, and the
    command-line options that each set one of its settings: (option, settings field).
    """

    module: str
    driver_class: str
    settings_class: str
    help: str
    options: tuple[tuple[str, str], ...] = ()


BACKENDS: dict[str, Backend] = {
    "arcos": Backend(
        "phalanx.drivers.arcos",
        "ArcosDriver",
        "ArcosSettings",
        "Pioneer P3DX over its ARCOS protocol, on a serial port or TCP",
        options=(("--arcos-port", "port"), ("--arcos-tcp", "tcp"), ("--baud", "baud")),
    ),
    "canopen": Backend(
        "phalanx.drivers.canopen",
        "CanopenDriver",
        "CanopenSettings",
        "two CiA 402 wheel drives on a CAN bus (python-can, canopen)",
        options=(("--can-channel", "channel"), ("--can-interface", "interface")),
    ),
}


def backend_names() -> tuple[str, ...]:
    """The registered backends' names, sorted."""
    return tuple(sorted(BACKENDS))


def backend(name: str) -> Backend:
    """Backend `name`'s entry; ConfigError listing the known names otherwise."""
    entry = BACKENDS.get(name)
    if entry is None:
        close = difflib.get_close_matches(name, BACKENDS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        known = ", ".join(backend_names())
        raise ConfigError(f"unknown driver backend {name!r}{hint}; backends: {known}")
    return entry


def settings_from_options(name: str, given: Mapping[str, object]) -> dict[str, object]:
    """The settings of driver `name` (a backend, or `sim`) that backend options set.

    `given` maps each option (`--arcos-tcp`) to its value, None for one not given. A
    ConfigError for an option no backend declares, or one of another backend than `name`.
    """
    owners = {
        option: (owner, field)
        for owner, entry in BACKENDS.items()
        for option, field in entry.options
    }
    values: dict[str, object] = {}
    for option, value in given.items():
        if value is None:
            continue
        if option not in owners:
            raise ConfigError(f"{option} is no driver backend's option")
        owner, field = owners[option]
        if owner != name:
            raise ConfigError(f"{option} is an option of --driver {owner}, not {name}")
        values[field] = value
    return values


def settings_model(name: str) -> type[BaseModel]:
    """The pydantic model of backend `name`'s settings (imports the backend)."""
    return cast(type[BaseModel], _load(name, backend(name).settings_class))


def validate_settings(
    name: str, settings: Mapping[str, Any] | BaseModel, *, source: str | None = None
) -> BaseModel:
    """`settings` checked by backend `name`'s own model.

    A mapping is validated (defaults filled in); an instance of the model is taken as it
    is. Otherwise ConfigError, from `source` (default "<name> driver settings") with the
    field and, for a misspelt key, the closest valid one.
    """
    model = settings_model(name)
    where = source or f"{name} driver settings"
    if isinstance(settings, model):
        return settings
    if isinstance(settings, BaseModel):
        raise ConfigError(f"{where}: expected {model.__name__}, got {type(settings).__name__}")
    return validate_data(model, settings, source=where)


def open_driver(
    name: str, settings: Mapping[str, Any] | BaseModel, *, robot: RobotParams
) -> Driver:
    """Backend `name`'s driver for `robot`, not yet connected, from checked `settings`.

    ConfigError for an unknown name or invalid settings; DriverUnavailable if the
    backend's library cannot be imported.
    """
    checked = validate_settings(name, settings)
    driver_class = _load(name, backend(name).driver_class)
    return cast("Driver", driver_class(checked, robot=robot))


def _load(name: str, attribute: str) -> Any:
    module_name = backend(name).module
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverUnavailable(f"driver backend {name!r} cannot be loaded: {exc}") from exc
    return getattr(module, attribute)
