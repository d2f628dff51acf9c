"""The `[localisation]` table: sources, their noise, and the errors a misspelt key gets."""

from __future__ import annotations

from pathlib import Path

import pytest

from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.errors import ConfigError

SCENARIOS = CONFIG_ROOT / "scenarios"
WEDGE = SCENARIOS / "paper_wedge.toml"


def _with(tmp_path: Path, table: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(WEDGE.read_text() + "\n" + table)
    return path


def test_the_papers_scenarios_keep_perfect_sensing() -> None:
    for name in ("wedge", "inline", "collateral"):
        scenario = load_scenario(SCENARIOS / f"paper_{name}.toml")
        assert not scenario.localisation.estimator
        assert not scenario.localisation.odometry.any


@pytest.mark.parametrize("path", sorted(SCENARIOS.glob("real_*.toml")), ids=lambda p: p.stem)
def test_the_real_scenarios_carry_a_realistic_set(path: Path) -> None:
    loc = load_scenario(path).localisation
    assert loc.estimator
    assert loc.odometry.any
    assert loc.markers is not None


def test_a_misspelt_key_names_its_path_and_the_likely_one(tmp_path: Path) -> None:
    path = _with(tmp_path, "[localisation]\nestimator = true\n[localisation.mocap]\nrat_hz = 50\n")
    with pytest.raises(ConfigError) as caught:
        load_scenario(path)
    assert "localisation.mocap.rat_hz" in str(caught.value)
    assert "did you mean 'rate_hz'" in str(caught.value)


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["localisation.markers={}"], "need `estimator = true`"),
        (["localisation.estimator=true", "localisation.mocap={ std_m = 0.0 }"], "std_m"),
        (["localisation.estimator=true", "localisation.markers={ min_range_m = 6.0 }"],
         "min_range_m must be below max_range_m"),
        (["noise.odometry_v_std_frac=0.02", "localisation.odometry={ walk_std_m = 0.001 }"],
         "not both"),
    ],
)  # fmt: skip
def test_inconsistent_sensing_is_refused(overrides: list[str], expected: str) -> None:
    with pytest.raises(ConfigError, match=expected):
        apply_overrides(load_scenario(WEDGE), overrides)


def test_the_example_camera_calibration_loads() -> None:
    from phalanx.core.config_files import validate_file
    from phalanx.core.localisation import CameraCalibration

    calibration = validate_file(CameraCalibration, CONFIG_ROOT / "cameras" / "example_720p.toml")
    assert calibration.width_px == 1280
    assert calibration.mount_x_m == 0.12
