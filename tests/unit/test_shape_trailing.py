"""A column's robots past the second trail: the leader's turns and the whole shape's free
way are reckoned without them; the deadlock's turns still swing the whole shape."""

from __future__ import annotations

import math

import numpy as np
import pytest

from phalanx.agents.navigation.steering import RIGID_SPEED_SHARE
from phalanx.agents.shape import Shape
from phalanx.core.config import NavigationConfig
from phalanx.core.config_files import load_robot
from phalanx.core.formation import Formation, resolve_formation
from phalanx.core.limits import KinematicLimits
from phalanx.core.scenarios import formation_shape

ROBOT = load_robot("p3dx")
LIMITS = KinematicLimits.from_params(ROBOT)


def shape_of(robot_id: str, formation: Formation) -> Shape:
    return Shape(
        robot_id, formation, radius_m=ROBOT.radius_m, nav=NavigationConfig(), limits=LIMITS,
        dt_s=0.1,
    )  # fmt: skip


def test_a_column_led_from_its_head_turns_as_fast_as_its_second_robot_allows() -> None:
    column = shape_of("r1", resolve_formation(formation_shape("inline", 5)))
    assert column.trailing == {"r3", "r4", "r5"}
    assert column.reach_m == pytest.approx(1.0)
    (second,) = column.follower_slots
    assert (second.x_m, second.y_m) == pytest.approx((-1.0, 0.0))
    # The slot 1 m behind swings at omega x 1 m: at most the rigid share of v_max.
    assert column.turn_rate_radps() == pytest.approx(
        min(LIMITS.omega_max_radps, RIGID_SPEED_SHARE * LIMITS.v_max_mps / 1.0)
    )


def test_a_column_led_from_its_middle_reckons_with_the_robots_ahead_of_it() -> None:
    # Re-rooted at r3: r2 and r1 are ahead of it (they do not trail), r4 tracks the
    # leader itself, r5 trails r4.
    column = shape_of("r3", resolve_formation(formation_shape("inline", 5)))
    assert column.trailing == {"r5"}
    assert column.reach_m == pytest.approx(2.0)


@pytest.mark.parametrize("kind", ["wedge", "collateral"])
def test_no_robot_of_a_wedge_or_a_line_trails(kind: str) -> None:
    formation = resolve_formation(formation_shape(kind, 5))  # type: ignore[arg-type]
    shape = shape_of("r1", formation)
    assert shape.trailing == frozenset()
    furthest = max(math.hypot(p.x_m, p.y_m) for p in formation.positions.values())
    assert shape.reach_m == pytest.approx(furthest)
    assert len(shape.follower_slots) == 4


def test_a_trailing_robot_still_counts_where_its_own_slot_matters() -> None:
    # Masking, the slot each robot steers for and the shape's own width still know
    # every robot: only the leader's navigating turns leave the trailing ones out.
    column = shape_of("r1", resolve_formation(formation_shape("inline", 5)))
    assert set(column.offsets) == {"r1", "r2", "r3", "r4", "r5"}
    tail = shape_of("r5", resolve_formation(formation_shape("inline", 5)))
    assert tail.formation.slot_of("r5", "r4").x_m == pytest.approx(-1.0)
    # Without the trailing robots a turn on the spot is limited by the second robot
    # alone: 4x what the whole column as one rigid body allows, which the deadlock's
    # turns (and its question whether the shape can turn round here) keep.
    rigid = RIGID_SPEED_SHARE * LIMITS.v_max_mps / 4.0
    assert column.turn_rate_radps(rigid=True) == pytest.approx(rigid)
    assert column.turn_rate_radps() == pytest.approx(min(LIMITS.omega_max_radps, 4.0 * rigid))
    near = (np.array([2.0]), np.array([0.0]))  # an echo 2 m ahead
    assert column.sweep_clear(near)  # 1 m + radius + margin < 2 m
    assert not column.sweep_clear(near, rigid=True)  # 4 m: the whole column's swing
