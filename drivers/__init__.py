"""Robot drivers: the `Driver` protocol, shared safety, and the backends, chosen by name.

`BACKENDS` says where each backend's driver and settings classes live. A backend's module,
and with it its hardware library (pyserial, python-can, canopen), is imported only when
that backend is asked for: importing `phalanx.drivers` imports none of them. Each backend
declares its settings once, as its own pydantic model, and every backend class is built
the same way, `Driver(settings, *, robot=robot_params)`:

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
    """Where a backend lives (imported on first use) and what it is, in one line."""

    module: str
    driver_class: str
    settings_class: str
    help: str


BACKENDS: dict[str, Backend] = {
    "arcos": Backend(
        "phalanx.drivers.arcos",
        "ArcosDriver",
        "ArcosSettings",
        "Pioneer P3DX over its ARCOS protocol, on a serial port or TCP",
    ),
    "canopen": Backend(
        "phalanx.drivers.canopen",
        "CanopenDriver",
        "CanopenSettings",
        "two CiA 402 wheel drives on a CAN bus (python-can, canopen)",
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
