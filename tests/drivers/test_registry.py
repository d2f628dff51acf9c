"""The driver registry: backends by name, settings checked by each backend's own model,
hardware libraries imported only when a backend is used, and `phalanx agent --driver`."""

from __future__ import annotations

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from phalanx.cli import app
from phalanx.core.config_files import CONFIG_ROOT, load_robot
from phalanx.core.errors import ConfigError
from phalanx.drivers import BACKENDS, backend_names, open_driver, settings_model
from phalanx.drivers.arcos import ArcosDriver, ArcosSettings
from phalanx.drivers.base import Driver
from phalanx.drivers.canopen import CanopenDriver, CanopenSettings
from phalanx.runtime.process_spec import AgentSpec

pytestmark = pytest.mark.drivers
ROBOT = load_robot("p3dx")
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
# Enough for each backend's model; building a driver opens nothing.
MINIMAL: dict[str, dict[str, object]] = {"arcos": {"tcp": "127.0.0.1:8101"}, "canopen": {}}


def test_the_backends_are_arcos_and_canopen_and_sim_is_not_one() -> None:
    assert backend_names() == ("arcos", "canopen")
    assert "sim" not in BACKENDS
    assert settings_model("arcos") is ArcosSettings
    assert settings_model("canopen") is CanopenSettings
    assert all(entry.help for entry in BACKENDS.values())


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_backend_is_built_the_same_way(name: str) -> None:
    driver = open_driver(name, MINIMAL[name], robot=ROBOT)
    try:
        assert isinstance(driver, Driver)
        assert driver.name == name
        assert isinstance(driver.settings, settings_model(name))  # type: ignore[attr-defined]
    finally:
        driver.close()  # never connected: nothing to release, and no error


def test_an_unknown_backend_is_named_with_a_hint_and_the_known_ones() -> None:
    with pytest.raises(ConfigError) as caught:
        open_driver("arcs", {}, robot=ROBOT)
    assert "unknown driver backend 'arcs' (did you mean 'arcos'?)" in str(caught.value)
    assert "backends: arcos, canopen" in str(caught.value)
    with pytest.raises(ConfigError, match="backends: arcos, canopen"):
        settings_model("sim")


def test_settings_are_checked_by_the_backends_own_model() -> None:
    with pytest.raises(ConfigError) as caught:
        open_driver("arcos", {"port": "/dev/ttyUSB0", "bauds": 19200}, robot=ROBOT)
    assert "arcos driver settings: invalid ArcosSettings" in str(caught.value)
    assert "bauds: Extra inputs are not permitted (did you mean 'baud'?)" in str(caught.value)
    with pytest.raises(ConfigError, match="give exactly one of port"):
        open_driver("arcos", {}, robot=ROBOT)
    with pytest.raises(ConfigError, match="wheel_radius_m: Extra inputs"):
        open_driver("canopen", {"wheel_radius_m": 0.1}, robot=ROBOT)  # the robot file's now
    with pytest.raises(ConfigError, match="expected CanopenSettings, got ArcosSettings"):
        open_driver("canopen", ArcosSettings(tcp="127.0.0.1:1"), robot=ROBOT)
    given = CanopenSettings(interface="virtual", bitrate=250_000)
    driver = open_driver("canopen", given, robot=ROBOT)
    assert isinstance(driver, CanopenDriver)
    assert driver.settings is given
    driver.close()


def test_importing_the_drivers_imports_no_hardware_library() -> None:
    code = (
        "import sys\n"
        "import phalanx.drivers, phalanx.drivers.base, phalanx.drivers.safety\n"
        "phalanx.drivers.backend_names()\n"
        "print(sorted(m for m in ('can', 'canopen', 'serial') if m in sys.modules))\n"
        "phalanx.drivers.settings_model('arcos')\n"
        "print('serial' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.split() == ["[]", "True"]  # and the backend's, once asked for


def test_an_unknown_driver_on_the_agent_command_line_is_a_clean_usage_error() -> None:
    argv = ["agent", str(WEDGE), "--robot", "r1", "--driver", "arcs"]
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 2, result.output
    assert "'arcs'" in result.output
    assert "did you mean 'arcos'" in result.output
    assert "Traceback" not in result.output
    assert isinstance(result.exception, SystemExit)


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--driver", "nonsense"], "sim, arcos, canopen"),
        (["--driver", "arcos"], "exactly one of port"),
        (["--driver", "arcos", "--arcos-tcp", "h:1", "--driver-setting", "baud=x"], "baud"),
        (["--driver", "canopen", "--arcos-port", "/dev/ttyS0"], "--driver arcos"),
        (["--driver", "canopen", "--driver-setting", "bitrate"], "KEY=VALUE"),
        (["--driver-setting", "port=1"], "sim driver has no settings"),
    ],
)
def test_bad_driver_options_are_named_without_a_traceback(extra: list[str], expected: str) -> None:
    result = CliRunner().invoke(app, ["agent", str(WEDGE), "--robot", "r1", *extra])
    assert result.exit_code == 2, result.output
    assert expected in " ".join(result.output.split()), result.output
    assert "Traceback" not in result.output


def _spec_of(*options: str) -> AgentSpec:
    """The spec `phalanx agent` makes of its options (the runtime builds the agent from it)."""
    argv = ["agent", str(WEDGE), "--robot", "r1", *options, "--print-spec"]
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 0, result.output
    return AgentSpec.model_validate_json(result.output)


def test_the_agent_fills_the_backends_settings_from_its_options() -> None:
    arcos = _spec_of(
        "--driver", "arcos", "--arcos-port", "/dev/ttyUSB0", "--baud", "19200",
        "--driver-setting", "sonar=false", "--driver-setting", "pulse_s=0.25",
    )  # fmt: skip
    assert arcos.driver.name == "arcos"
    assert arcos.driver.settings == ArcosSettings(
        port="/dev/ttyUSB0", baud=19200, sonar=False, pulse_s=0.25
    )
    canopen = _spec_of(
        "--driver", "canopen", "--can-interface", "virtual", "--driver-setting", "channel=bus-7",
        "--driver-setting", "bitrate=250000", "--driver-setting", "left_sign = -1",
    )  # fmt: skip
    expected = CanopenSettings(interface="virtual", channel="bus-7", bitrate=250_000, left_sign=-1)
    assert canopen.driver.settings == expected
    assert _spec_of().driver.settings is None  # sim: the world moves the robot
    # The factory opens each through the registry, as every backend is built.
    for spec, kind in ((arcos, ArcosDriver), (canopen, CanopenDriver)):
        assert spec.driver.settings is not None
        driver = open_driver(spec.driver.name, spec.driver.settings, robot=ROBOT)
        assert isinstance(driver, kind)
        assert driver.settings == spec.driver.settings
        driver.close()
