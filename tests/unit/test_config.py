from pathlib import Path

import pytest
from pydantic import ValidationError

from phalanx.core.config import Scenario
from phalanx.core.config_files import (
    CONFIG_ROOT,
    apply_overrides,
    load_robot,
    load_scenario,
    parse_assignment,
    validate_data,
)
from phalanx.core.errors import ConfigError

SCENARIOS = CONFIG_ROOT / "scenarios"


def test_every_shipped_scenario_loads() -> None:
    files = sorted(SCENARIOS.glob("*.toml"))
    assert len(files) >= 3
    for path in files:
        assert load_scenario(path).name


def test_p3dx_has_sixteen_sonars_and_the_paper_limits_tighten_it() -> None:
    robot = load_robot("p3dx")
    assert len(robot.sonar.units) == 16
    scenario = load_scenario(SCENARIOS / "paper_wedge.toml")
    assert scenario.limits.v_max_mps == pytest.approx(0.3)
    assert scenario.limits.omega_max_degps == pytest.approx(40.0)
    assert robot.v_max_mps > 0.3


def test_unknown_key_names_file_field_and_hint(tmp_path: Path) -> None:
    text = (
        (SCENARIOS / "paper_wedge.toml")
        .read_text()
        .replace("reverse_speed_mps", "reverse_sped_mps")
    )
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    message = str(err.value)
    assert str(path) in message
    assert "deadlock.reverse_sped_mps" in message
    assert "did you mean 'reverse_speed_mps'" in message


def test_wrong_value_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(
        (SCENARIOS / "paper_wedge.toml")
        .read_text()
        .replace("control_rate_hz = 10.0", "control_rate_hz = -1")
    )
    with pytest.raises(ConfigError, match="control_rate_hz"):
        load_scenario(path)


def test_invalid_toml_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text("name = ")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(path)
    with pytest.raises(ConfigError, match="no such file"):
        load_scenario(tmp_path / "absent.toml")


def test_slots_must_match_robots() -> None:
    data = load_scenario(SCENARIOS / "paper_wedge.toml").model_dump()
    data["robots"] = data["robots"][:2]
    with pytest.raises(ConfigError, match="formation slots"):
        validate_data(Scenario, data, source="test")


def test_overrides_apply_and_validate() -> None:
    scenario = load_scenario(SCENARIOS / "paper_wedge.toml")
    changed = apply_overrides(scenario, ["controller.kind=icr", "noise.sonar_std_m=0.02"])
    assert changed.controller.kind == "icr"
    assert changed.noise.sonar_std_m == pytest.approx(0.02)
    with pytest.raises(ConfigError, match=r"controller\.kind"):
        apply_overrides(scenario, ["controller.kind=fancy"])
    with pytest.raises(ConfigError, match="no field"):
        apply_overrides(scenario, ["nothing.here=1"])


def test_parse_assignment_splits_path_and_value() -> None:
    assert parse_assignment(" noise.sonar_std_m = 0.02") == ("noise.sonar_std_m", 0.02)
    assert parse_assignment("formation.slots.1.l_m=3") == ("formation.slots.1.l_m", 3)
    assert parse_assignment("controller.kind=ours") == ("controller.kind", "ours")
    assert parse_assignment('name="a=b"') == ("name", "a=b")
    assert parse_assignment("name=a=b") == ("name", "a=b")
    for bad in ["duration_s", "=60", "  =60"]:
        with pytest.raises(ConfigError, match=r"expected PATH=VALUE, e\.g\. duration_s=60"):
            parse_assignment(bad)
    scenario = load_scenario(SCENARIOS / "paper_wedge.toml")
    with pytest.raises(ConfigError, match=r"^here: --set 'duration_s': expected PATH=VALUE"):
        apply_overrides(scenario, ["duration_s"], source="here")


def test_a_scenario_bounds_the_resources_it_may_ask_for() -> None:
    from phalanx.core.config import MAX_ROBOTS, Scenario

    base = load_scenario(SCENARIOS / "paper_wedge.toml").model_dump()
    robots = [{"id": f"r{i}"} for i in range(MAX_ROBOTS + 1)]
    slots = [{"robot": "r0", "x_m": 0.0, "y_m": 0.0}]
    slots += [{"robot": f"r{i}", "follows": "r0", "l_m": 1.0 + i, "phi_deg": 180.0}
              for i in range(1, MAX_ROBOTS + 1)]  # fmt: skip
    with pytest.raises(ValidationError, match="at most 1000"):
        Scenario.model_validate({**base, "robots": robots, "formation": {"slots": slots}})
    with pytest.raises(ValidationError, match="robot-steps"):
        Scenario.model_validate({**base, "duration_s": 86_400.0, "control_rate_hz": 100.0})
    with pytest.raises(ValidationError, match="finite"):
        Scenario.model_validate({**base, "seed": 1, "comm_delay_s": float("nan")})


def test_emergency_braking_is_never_softer_than_the_comfortable_one() -> None:
    from phalanx.core.robot_params import RobotParams

    p3dx = load_robot("p3dx").model_dump()
    with pytest.raises(ValidationError, match="emergency_decel_mps2"):
        RobotParams.model_validate({**p3dx, "emergency_decel_mps2": 0.1})
    plain = RobotParams.model_validate(
        {**p3dx, "emergency_decel_mps2": None, "emergency_rot_decel_degps2": None}
    )
    assert plain.emergency_decel == (plain.decel_mps2, plain.rot_accel_radps2)
