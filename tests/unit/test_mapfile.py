"""Prior maps and saved fleet maps in ROS map_server's format (image + YAML header)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from phalanx.agents.navigation import FleetMap, OccupancyMap
from phalanx.agents.perception import SonarGeometry
from phalanx.core.config import CircleObstacle, NoiseConfig, WorldConfig
from phalanx.core.config_files import load_robot
from phalanx.core.errors import ConfigError
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.mapfile import FREE, OCCUPIED, UNKNOWN, load_map, save_map
from phalanx.core.peers import Scan
from phalanx.simulator.world import World


def _header(path: Path, **fields: object) -> Path:
    base = {"image": "m.png", "resolution": 0.05, "origin": "[-1.0, -2.0, 0.0]",
            "occupied_thresh": 0.65, "free_thresh": 0.196, "negate": 0}  # fmt: skip
    base.update(fields)
    path.write_text("".join(f"{k}: {v}\n" for k, v in base.items()), encoding="utf-8")
    return path


def test_a_png_is_read_as_map_server_reads_it(tmp_path: Path) -> None:
    pixels = np.full((4, 6), 205, dtype=np.uint8)  # unknown
    pixels[0, 0] = 0  # top-left: occupied, and the map's last row
    pixels[3, 5] = 254  # bottom-right: free, the map's first row
    Image.fromarray(pixels).save(tmp_path / "m.png")
    grid = load_map(_header(tmp_path / "m.yaml"))
    assert grid.cells.shape == (4, 6)
    assert grid.cells[3, 0] == OCCUPIED
    assert grid.cells[0, 5] == FREE
    assert grid.cells[1, 1] == UNKNOWN
    x, y = grid.centres(OCCUPIED)
    assert (float(x[0]), float(y[0])) == pytest.approx((-1.0 + 0.025, -2.0 + 3.5 * 0.05))
    negated = load_map(_header(tmp_path / "n.yaml", negate=1))
    assert negated.cells[3, 0] == FREE
    assert negated.cells[0, 5] == OCCUPIED


def test_the_fleet_map_saved_and_loaded_again_is_the_same(tmp_path: Path) -> None:
    grid = OccupancyMap(Vec2(0.0, 0.0), half_size_m=5.0)
    grid.evidence[4, 7] = 6
    grid.seen[3:6, 2:9] = True
    save_map(grid.to_grid(), tmp_path / "fleet.yaml")
    back = load_map(tmp_path / "fleet.yaml")
    assert np.array_equal(back.cells, grid.to_grid().cells)
    assert back.origin == (-5.0, -5.0, 0.0)
    assert back.resolution_m == 0.5
    again = OccupancyMap(Vec2(0.0, 0.0), half_size_m=5.0)
    again.load_prior(back)
    assert np.array_equal(again.occupied(), grid.occupied())


@pytest.mark.parametrize(
    ("fields", "says"),
    [
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": "lots"}, "resolution"),
        ({"origin": "[1.0, 2.0]"}, "origin"),
        ({"origin": "[.nan, 0.0, 0.0]"}, "finite"),
        ({"origin": "[1e9, 0.0, 0.0]"}, "within"),
        ({"free_thresh": 0.9}, "below occupied_thresh"),
        ({"occupied_thresh": 2}, "occupied_thresh"),
        ({"negate": 3}, "negate"),
        ({"mode": "fancy"}, "mode"),
        ({"colour": "red"}, "colour"),
        ({"image": "missing.png"}, "cannot read the map image"),
    ],
)
def test_a_bad_header_says_what_was_expected(tmp_path: Path, fields: dict, says: str) -> None:
    Image.fromarray(np.zeros((2, 2), dtype=np.uint8)).save(tmp_path / "m.png")
    with pytest.raises(ConfigError, match=says):
        load_map(_header(tmp_path / "m.yaml", **fields))


def test_not_yaml_not_a_mapping_too_big_or_not_an_image(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("image: [unclosed\n", encoding="utf-8")
    (tmp_path / "b.yaml").write_text("- 1\n- 2\n", encoding="utf-8")
    (tmp_path / "c.yaml").write_text("#" * 70_000, encoding="utf-8")
    (tmp_path / "m.png").write_bytes(b"not a picture")
    for name, says in (("a", "YAML"), ("b", "mapping"), ("c", "at most")):
        with pytest.raises(ConfigError, match=says):
            load_map(tmp_path / f"{name}.yaml")
    with pytest.raises(ConfigError, match="cannot read the map image"):
        load_map(_header(tmp_path / "d.yaml"))


def test_scans_from_many_robots_make_one_map_whatever_order_they_arrive_in() -> None:
    sonar = SonarGeometry.from_params(load_robot("p3dx"))
    units = sonar.unit_x_m.size
    ranges = tuple([1.0] * 4 + [5.0] * (units - 4))
    echo = tuple([True] * 4 + [False] * (units - 4))
    scans = [Scan(r, t, x, 0.0, 0.0, ranges, echo)
             for t in (0.1, 0.2) for r, x in (("r1", 0.0), ("r2", -1.0))]  # fmt: skip
    a = FleetMap(Vec2(0.0, 0.0), sonar=sonar, order=("r1", "r2"))
    a.add(scans)
    b = FleetMap(Vec2(0.0, 0.0), sonar=sonar, order=("r1", "r2"))
    b.add(reversed(scans[:2]))  # a step's scans in any order, and heard twice
    b.add([*reversed(scans), *scans])
    assert (a.scans_added, b.scans_added) == (4, 4)
    assert np.array_equal(a.map.evidence, b.map.evidence)
    assert a.map.occupied().any()
    late = FleetMap(Vec2(0.0, 0.0), sonar=sonar, order=("r1", "r2"))
    late.add(scans[2:])
    late.add(scans[:2])  # older than what each robot already gave: dropped
    assert late.scans_added == 2


def test_echoes_of_the_fleets_own_robots_are_not_obstacles_on_its_map() -> None:
    """Three robots in a simulated world with one post, sharing what their rings hear
    with nothing masked: where a robot stands the map stays clear, while the post is on
    it. Where the others' scans are too old to say where they are, they are obstacles."""
    robot = load_robot("p3dx")
    sonar = SonarGeometry.from_params(robot)
    post = CircleObstacle(x_m=0.0, y_m=-1.6, radius_m=0.3)
    world = World(robot=robot, world=WorldConfig(circles=(post,)), noise=NoiseConfig())
    places = {"r1": Pose2D(0.0, 0.0, 0.0), "r2": Pose2D(1.6, 0.3, 0.0), "r3": Pose2D(0.2, 1.5, 1.0)}
    for robot_id, pose in places.items():
        world.add_robot(robot_id, pose)
    _, rows = world.statuses()

    def scans(stamps: dict[str, float]) -> list[Scan]:
        return [
            Scan(r, stamps[r], p.x_m, p.y_m, p.theta_rad, tuple(row.tolist()),
                 tuple(sonar.ranged(row).tolist()))
            for (r, p), row in zip(places.items(), rows, strict=True)
        ]  # fmt: skip

    robots = [places["r2"].position, places["r3"].position]
    post_at = [Vec2(post.x_m, post.y_m)]
    fleet = FleetMap(Vec2(0.0, 0.0), sonar=sonar, order=tuple(places))
    fleet.add(scans({"r1": 1.0, "r2": 1.0, "r3": 1.0}))
    assert fleet.robot_echoes >= 2
    assert fleet.map.clear_of(robots, 0.3).all()
    assert not fleet.map.clear_of(post_at, 0.3).any()
    # r1 scanned a second after the others: where they were then says nothing of now
    stale = FleetMap(Vec2(0.0, 0.0), sonar=sonar, order=tuple(places))
    stale.add(scans({"r1": 2.0, "r2": 1.0, "r3": 1.0}))
    assert not stale.map.clear_of(robots, 0.3).any()
    assert not stale.map.clear_of(post_at, 0.3).any()
