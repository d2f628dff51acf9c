import math

import pytest

from phalanx.core.config import FormationConfig, SlotConfig
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.errors import ConfigError
from phalanx.core.formation import Formation, resolve_formation, scenario_formation
from phalanx.core.geometry import Pose2D
from phalanx.core.scenarios import grid_scenario


def _wedge() -> FormationConfig:
    return FormationConfig(
        slots=(
            SlotConfig(robot="r1", x_m=0.0, y_m=0.0),
            SlotConfig(robot="r2", follows="r1", l_m=1.0, phi_deg=135.0),
            SlotConfig(robot="r3", follows="r1", l_m=1.0, phi_deg=225.0),
        )
    )


def test_wedge_is_behind_left_and_behind_right() -> None:
    f = resolve_formation(_wedge())
    r2, r3 = f.positions["r2"], f.positions["r3"]
    assert (r2.x_m, r2.y_m) == pytest.approx((-math.sqrt(0.5), math.sqrt(0.5)))
    assert (r3.x_m, r3.y_m) == pytest.approx((-math.sqrt(0.5), -math.sqrt(0.5)))
    assert f.root == "r1"
    assert f.followers_of("r1") == ("r2", "r3")


def test_any_pair_has_a_slot_so_leadership_can_pass() -> None:
    f = resolve_formation(_wedge())
    l_m, phi = f.polar_of("r3", "r2")  # r3 is straight right of r2
    assert l_m == pytest.approx(math.sqrt(2.0))
    assert math.degrees(phi) == pytest.approx(270.0)


def test_chain_resolves_through_parents() -> None:
    f = resolve_formation(
        FormationConfig(
            slots=(
                SlotConfig(robot="c", follows="b", l_m=1.0, phi_deg=180.0),
                SlotConfig(robot="b", follows="a", l_m=1.0, phi_deg=180.0),
                SlotConfig(robot="a", x_m=0.0, y_m=0.0),
            )
        )
    )
    assert f.positions["c"].x_m == pytest.approx(-2.0)
    assert f.leader_of("c") == "b"


def test_slot_pose_rotates_with_the_root() -> None:
    f = resolve_formation(_wedge())
    pose = f.slot_pose("r2", Pose2D(1.0, 2.0, math.pi / 2))
    assert (pose.x_m, pose.y_m) == pytest.approx((1.0 - math.sqrt(0.5), 2.0 - math.sqrt(0.5)))
    assert pose.theta_rad == pytest.approx(math.pi / 2)


def test_cycle_is_a_config_error() -> None:
    config = FormationConfig(
        slots=(
            SlotConfig(robot="root", x_m=0.0, y_m=0.0),
            SlotConfig(robot="a", follows="b", l_m=1.0, phi_deg=180.0),
            SlotConfig(robot="b", follows="a", l_m=1.0, phi_deg=180.0),
        )
    )
    with pytest.raises(ConfigError, match="cycle"):
        resolve_formation(config)


def _ancestors(formation: Formation, robot: str) -> list[str]:
    chain = [robot]
    while (parent := formation.parents[chain[-1]]) is not None:
        chain.append(parent)
    return chain


def test_tree_paths_go_up_to_the_common_ancestor_and_down() -> None:
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    formation = scenario_formation(grid_scenario(base, 40))  # a multi-leader tree
    for start in formation.parents:
        for goal in formation.parents:
            up, down = _ancestors(formation, start), _ancestors(formation, goal)
            common = next(r for r in up if r in down)
            expected = up[1 : up.index(common) + 1] + down[: down.index(common)][::-1]
            assert formation.tree_path(start, goal) == tuple(expected)
    with pytest.raises(ValueError, match="not connected"):
        formation.tree_path("r1", "nobody")
