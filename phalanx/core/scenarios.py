"""Scenarios built in code: grid formations for scaling, and the navigation scenarios
(corridors, dead ends, seeded obstacle fields, a narrow passage) for 3 or 5 robots in
wedge, inline and collateral shapes, as the files in `configs/scenarios/nav_*.toml` and
the Monte-Carlo benchmark use them.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

from phalanx.core.config import (
    CircleObstacle,
    FormationConfig,
    ObstacleField,
    PolygonObstacle,
    RobotEntry,
    Scenario,
    SensorEvent,
    SlotConfig,
    StartPose,
    WorldConfig,
)
from phalanx.core.config_files import toml_value, validate_data

Shape = Literal["wedge", "inline", "collateral"]
Course = Literal["corridor", "deadend", "field", "narrow"]
SHAPES: tuple[Shape, ...] = ("wedge", "inline", "collateral")
COURSES: tuple[Course, ...] = ("corridor", "deadend", "field", "narrow")
# The narrow passage's gap (m): narrower than a wedge or a line of 3 (1.9 and 2.5 m across
# with the robots), wider than a column (0.5 m).
NARROW_GAP_M = 1.6
SPACING_M = 1.0
_PLACEMENT_TRIES = 50


def grid_formation(n: int, *, spacing_m: float = 2.0) -> FormationConfig:
    """`n` robots on a square grid behind the root, each following its neighbour.

    Row 0 is a chain to the right of the root; every other row hangs off the robot in
    front of it, so leader-state traffic stays O(followers of each robot).
    """
    cols = max(1, math.ceil(math.sqrt(n)))
    slots = []
    for i in range(n):
        row, col = divmod(i, cols)
        follows = None if i == 0 else (f"g{i - 1}" if row == 0 else f"g{i - cols}")
        slots.append(
            SlotConfig(robot=f"g{i}", follows=follows, x_m=-row * spacing_m, y_m=-col * spacing_m)
        )
    return FormationConfig(slots=tuple(slots))


def grid_scenario(base: Scenario, n: int, *, duration_s: float | None = None) -> Scenario:
    """`base` (its leader script, events, controller) with an `n`-robot grid formation."""
    formation = grid_formation(n)
    robots = tuple(
        RobotEntry(id=s.robot, start=StartPose(x_m=s.x_m or 0.0, y_m=s.y_m or 0.0))
        for s in formation.slots
    )
    data = base.model_dump()
    data.update(
        name=f"{base.name}-grid{n}",
        formation=formation.model_dump(),
        robots=[r.model_dump() for r in robots],
        duration_s=duration_s or base.duration_s,
    )
    return validate_data(Scenario, data, source=f"grid scenario of {n} robots")


# --- formation shapes ------------------------------------------------------------------


def _shape_links(shape: Shape, n: int) -> list[tuple[str, str, float]]:
    """(robot, robot it follows, phi in deg) for robots r2..rn of a shape."""
    links = []
    for i in range(2, n + 1):
        if shape == "inline":
            links.append((f"r{i}", f"r{i - 1}", 180.0))
            continue
        left = i % 2 == 0  # even robots to the left, odd to the right
        parent = "r1" if i <= 3 else f"r{i - 2}"
        if shape == "wedge":
            links.append((f"r{i}", parent, 135.0 if left else 225.0))
        else:
            links.append((f"r{i}", parent, 90.0 if left else 270.0))
    return links


def formation_shape(shape: Shape, n: int, *, spacing_m: float = SPACING_M) -> FormationConfig:
    """`n` robots in a wedge (a V, 135/225 deg), inline (a chain, 180 deg) or collateral
    (abreast, 90/270 deg), `spacing_m` between neighbours; each tracks a neighbour.
    """
    if n < 1:
        raise ValueError("a formation needs at least one robot")
    slots = [SlotConfig(robot="r1", x_m=0.0, y_m=0.0)]
    slots += [
        SlotConfig(robot=rid, follows=parent, l_m=spacing_m, phi_deg=phi)
        for rid, parent, phi in _shape_links(shape, n)
    ]
    return FormationConfig(slots=tuple(slots))


def _slot_positions(formation: FormationConfig) -> dict[str, tuple[float, float]]:
    from phalanx.core.formation import resolve_formation

    resolved = resolve_formation(formation)
    return {r: (p.x_m, p.y_m) for r, p in resolved.positions.items()}


# --- obstacle fields -----------------------------------------------------------------


def obstacle_field(field: ObstacleField) -> tuple[CircleObstacle, ...]:
    """The circles of a seeded field: the same for the same seed, on every machine."""
    rng = np.random.default_rng(field.seed)
    placed: list[CircleObstacle] = []
    for _ in range(field.count * _PLACEMENT_TRIES):
        if len(placed) == field.count:
            break
        candidate = CircleObstacle(
            x_m=float(rng.uniform(field.x_min_m, field.x_max_m)),
            y_m=float(rng.uniform(field.y_min_m, field.y_max_m)),
            radius_m=float(rng.uniform(field.radius_min_m, field.radius_max_m)),
        )
        if _fits(candidate, placed, field):
            placed.append(candidate)
    return tuple(placed)


def _fits(c: CircleObstacle, placed: list[CircleObstacle], field: ObstacleField) -> bool:
    def gap(o: CircleObstacle) -> float:
        return math.hypot(c.x_m - o.x_m, c.y_m - o.y_m) - c.radius_m - o.radius_m

    clear_of_zones = all(gap(zone) > 0.0 for zone in field.keep_clear)
    return clear_of_zones and all(gap(o) >= field.min_gap_m for o in placed)


def signal_builder(
    start_s: float, *, robots: tuple[str, ...] = (), keep: tuple[SensorEvent, ...] = ()
) -> list[str]:
    """Overrides (`--set` strings) that block the group the paper's way instead of by a
    paper scenario's wall: every sonar of `robots` (all: ()) reads 0.3 m for 2 s from
    `start_s` (a scripted sensor event, as the paper's Simulink signal builder), with no
    obstacle in the world, beside the scenario's events to `keep`. For runs cut short,
    for blocking the group mid-turn, and for studies of something else than the wall.
    """
    block = SensorEvent(start_s=start_s, duration_s=2.0, robots=robots, range_m=0.3)
    events = ", ".join(_inline(e.model_dump(mode="json")) for e in (*keep, block))
    return ["world.polygons=[]", f"events=[{events}]"]


def _inline(table: dict[str, Any]) -> str:
    """A TOML inline table."""
    return "{" + ", ".join(f"{k} = {toml_value(v)}" for k, v in table.items()) + "}"


def resolve_world(world: WorldConfig) -> WorldConfig:
    """`world` with its seeded field (if any) turned into plain circles."""
    if world.field is None:
        return world
    circles = world.circles + obstacle_field(world.field)
    return world.model_copy(update={"circles": circles, "field": None})


# --- navigation courses ----------------------------------------------------------------


def _box(x0: float, y0: float, x1: float, y1: float) -> PolygonObstacle:
    return PolygonObstacle(vertices_m=((x0, y0), (x1, y0), (x1, y1), (x0, y1)))


def _span_m(formation: FormationConfig) -> float:
    ys = [y for _, y in _slot_positions(formation).values()]
    return max(ys) - min(ys) + 2 * 0.25


def _corridor(span_m: float) -> tuple[WorldConfig, tuple[float, float]]:
    """A straight corridor 2.5 m wider than the shape, with two staggered pillars that
    leave the shape room on one side only: the group has to weave, a robot to avoid.
    """
    half = span_m / 2 + 1.25
    walls = (_box(-4.0, half, 26.0, half + 0.3), _box(-4.0, -half - 0.3, 26.0, -half))
    pillars = (
        CircleObstacle(x_m=8.0, y_m=half - 0.9, radius_m=0.3),
        CircleObstacle(x_m=15.0, y_m=-half + 0.9, radius_m=0.3),
    )
    return WorldConfig(circles=pillars, polygons=walls), (22.0, 0.0)


def _deadend(span_m: float) -> tuple[WorldConfig, tuple[float, float]]:
    """A U-shaped trap open towards the start, 1.2 m wider than the shape (room to drive
    in, not to turn a wedge or a line round) and 8 m deep (its end out of sonar range
    from the mouth), with the goal behind it: the group drives in, finds the end, must
    back out in formation (the deadlock reverse), then goes round.
    """
    half = span_m / 2 + 0.6
    x0, x1 = 4.0, 12.0
    walls = (
        _box(x0, half, x1 + 0.3, half + 0.3),
        _box(x0, -half - 0.3, x1 + 0.3, -half),
        _box(x1, -half, x1 + 0.3, half),
    )
    return WorldConfig(polygons=walls), (19.0, 0.0)


def _field(span_m: float, seed: int, count: int) -> tuple[WorldConfig, tuple[float, float]]:
    """Seeded round obstacles between start and goal in an arena 12 m wide."""
    half = max(6.0, span_m / 2 + 3.0)
    walls = (_box(-4.0, half, 28.0, half + 0.3), _box(-4.0, -half - 0.3, 28.0, -half))
    field = ObstacleField(
        seed=seed,
        count=count,
        radius_min_m=0.2,
        radius_max_m=0.45,
        x_min_m=3.0,
        x_max_m=21.0,
        y_min_m=-half + 0.5,
        y_max_m=half - 0.5,
        min_gap_m=1.2,
        keep_clear=(
            CircleObstacle(x_m=-1.0, y_m=0.0, radius_m=span_m / 2 + 2.0),
            CircleObstacle(x_m=24.0, y_m=0.0, radius_m=2.0),
        ),
    )
    return WorldConfig(polygons=walls, field=field), (24.0, 0.0)


def _narrow(span_m: float) -> tuple[WorldConfig, tuple[float, float]]:
    """A wall across an arena 12 m wide with one gap `NARROW_GAP_M` wide, 8 m ahead, the
    goal 10 m beyond: a shape wider than the gap passes only folded into a column.
    """
    half, gap = max(6.0, span_m / 2 + 3.0), NARROW_GAP_M / 2
    walls = (
        _box(-4.0, half, 24.0, half + 0.3),
        _box(-4.0, -half - 0.3, 24.0, -half),
        _box(8.0, gap, 8.3, half),
        _box(8.0, -half, 8.3, -gap),
    )
    return WorldConfig(polygons=walls), (18.0, 0.0)


def navigation_scenario(
    course: Course,
    shape: Shape,
    n: int,
    *,
    seed: int = 0,
    obstacles: int = 18,
    overrides: dict[str, Any] | None = None,
) -> Scenario:
    """A navigation scenario: `n` robots in `shape` from the origin to a goal through a
    `corridor`, a `deadend` (U-shaped trap) or a seeded obstacle `field`.
    """
    formation = formation_shape(shape, n)
    span = _span_m(formation)
    if course == "corridor":
        world, goal = _corridor(span)
    elif course == "deadend":
        world, goal = _deadend(span)
    elif course == "narrow":
        world, goal = _narrow(span)
    else:
        world, goal = _field(span, seed, obstacles)
    positions = _slot_positions(formation)
    data: dict[str, Any] = {
        "name": f"nav-{course}-{shape}{n}" + (f"-s{seed}" if course == "field" else ""),
        "description": f"{n} robots, {shape}, to ({goal[0]:g}, {goal[1]:g}) {_THROUGH[course]}",
        # A line as wide as a collateral shape takes over 300 s to back out of the dead
        # end and go round it.
        "duration_s": 360.0 if course == "deadend" else 240.0,
        "seed": seed,
        "settle_s": 5.0,
        "initial_settle_s": 5.0,
        "limits": {"v_max_mps": 0.3, "omega_max_degps": 40.0},
        "formation": formation.model_dump(exclude_none=True),
        "robots": [
            {"id": rid, "start": {"x_m": x, "y_m": y, "theta_deg": 0.0}}
            for rid, (x, y) in positions.items()
        ],
        "navigation": {"waypoints": [list(goal)]},
        "deadlock": {
            # Out of a dead end straight back, as the paper (the way in was straight, and
            # a leader that does not turn keeps the followers' headings exact), once the
            # shape is turned back to the way it came in; elsewhere back along the path
            # driven, which is known to be free.
            "reverse_mode": "fixed" if course == "deadend" else "path",
            # Before the paper's straight reverse, time for every follower to settle
            # onto its slot, position then heading (`Track`, phalanx.agents.behaviours
            # .follower): a slot swung sideways by the turn back takes a turn, a short
            # drive and a turn: done within 12 s in all six dead ends (not a bound for
            # any start: a follower further off takes longer).
            "pause_s": 12.0 if course == "deadend" else 3.0,
            "safe_distance_m": 10.0 if course == "deadend" else 2.0,
            "turn_away_deg": 60.0,
            "escape_distance_m": 3.0,
        },
        "world": world.model_dump(exclude_none=True),
    }
    for path, value in (overrides or {}).items():
        _put(data, path.split("."), value)
    return validate_data(Scenario, data, source=f"navigation scenario {data['name']}")


_THROUGH = {
    "corridor": "along a corridor",
    "deadend": "past a dead end",
    "field": "through an obstacle field",
    "narrow": "through a gap narrower than the shape",
}


def _put(data: dict[str, Any], keys: list[str], value: Any) -> None:
    for key in keys[:-1]:
        data = data.setdefault(key, {})
    data[keys[-1]] = value


# --- TOML -------------------------------------------------------------------------------


def scenario_toml(scenario: Scenario, *, header: str = "") -> str:
    """`scenario` as a TOML scenario file (fields at their defaults left out)."""
    data = scenario.model_dump(mode="json", exclude_defaults=True)
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    lines += _toml_table(data, ())
    return "\n".join(lines).strip() + "\n"


def _toml_table(data: dict[str, Any], path: tuple[str, ...]) -> list[str]:
    scalars = {k: v for k, v in data.items() if not _is_table(v) and not _is_tables(v)}
    lines = [f"{k} = {toml_value(v)}" for k, v in scalars.items()]
    for key, value in data.items():
        if _is_table(value):
            lines += ["", f"[{'.'.join((*path, key))}]", *_toml_table(value, (*path, key))]
        elif _is_tables(value):
            for item in value:
                lines += ["", f"[[{'.'.join((*path, key))}]]", *_toml_table(item, (*path, key))]
    return lines


def _is_table(value: Any) -> bool:
    return isinstance(value, dict)


def _is_tables(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)
