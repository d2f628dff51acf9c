"""The viewer's layout as a real recording carries it: every 2D view draws y up, and each
robot has one colour in every view that draws one of its entities, never the bounds'.

A Telemetry writes a recording (live rows for some robots, a batch run's columns for
another); the blueprint and the transforms are read back from the file with Rerun's
own reader.
"""

from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.rigid_body import LiveErrors
from phalanx.telemetry.blueprint import MAP_FRAME, MAP_FRAME_ENTITY, ROOT_FRAME, robot_colours
from phalanx.telemetry.sinks import TelemetrySink
from phalanx.telemetry.stream import Telemetry

LIVE = ("r1", "r2")  # logged step by step, as agents do
BATCH = "r3"  # logged as a whole run's columns, as `phalanx run` does
IDS = (*LIVE, BATCH)
SONAR = load_robot("p3dx").sonar
COV = (0.01, 0.002, 0.0, 0.02, 0.0, 0.001)
OVERRIDE = re.compile(r"^/view/([^/]+)/ViewContents/overrides/(.+)/visualizers/[^/]+$")
UNCOLOURED = {"state"}  # the state timeline colours the states, not the robots


@dataclass
class Layout:
    """One blueprint as read back: each view's kind, properties and colour overrides."""

    kinds: dict[str, str] = field(default_factory=dict)  # view id -> class identifier
    target_frames: dict[str, str] = field(default_factory=dict)
    y_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    colours: dict[str, set[int]] = field(default_factory=lambda: defaultdict(set))  # entity


def record(path: Path) -> list[tuple[float, float]]:
    """A short recording of three robots through the real Telemetry; the positions."""
    sink = TelemetrySink(kind="file", path=path)
    positions = []
    with Telemetry(recording_id="layout-test", sink=sink) as tel:
        tel.log_world(circles=[(4.0, 6.0, 0.5)], polygons=[])
        tel.log_bounds(t_s=[0.0, 2.0], linear_pct=2.0, angular_pct=0.8,
                       v_max_mps=0.3, omega_max_radps=0.5)  # fmt: skip
        tel.send_blueprint(IDS)
        for k in range(20):
            t_s = 0.1 * k
            for n, rid in enumerate(LIVE):
                pose = Pose2D(0.1 * k, 2.0 + n, 0.3)
                positions.append((pose.x_m, pose.y_m))
                errors = LiveErrors(Pose2D(0.1 * k, 2.0 + n, 0.0), 1.0, 0.5, 2.0)
                tel.log_step(rid, t_s=t_s, step=k, pose=pose, cmd=Twist2D(0.2, 0.1),
                             measured=Twist2D(0.19, 0.1), tracking=errors if n else None,
                             sonar=SONAR, sonar_ranges_m=[1.0] * len(SONAR.units),
                             fsm_state="FORMATION_TRACK", leader_id="r1" if n else "",
                             cov=COV)  # fmt: skip
                tel.log_truth(rid, t_s=t_s, pose=pose)
        tel.log_transition("r2", t_s=0.5, source="IDLE", target="FORMATION_TRACK", reason="go")
        t = np.linspace(0.0, 2.0, 21)
        ones = np.ones_like(t)
        x, y = t, 4.0 + 0.5 * t
        positions += list(zip(x.tolist(), y.tolist(), strict=True))
        tel.log_columns(BATCH, t_s=t, x_m=x, y_m=y, theta_rad=0 * t, cmd_v=0.2 * ones,
                        cmd_omega=0 * t, meas_v=0.2 * ones, meas_omega=0 * t,
                        linear_pct=ones, angular_pct=ones, orientation_deg=ones)  # fmt: skip
        xy = np.column_stack([x, y])
        tel.log_estimates(BATCH, t_s=t, estimate=np.column_stack([xy, 0 * t]),
                          cov=np.tile(COV, (len(t), 1)), truth_xy=xy)  # fmt: skip
    return positions


def layouts(path: Path) -> list[Layout]:
    """Every blueprint in the recording (the first layout, the one framed at the end)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    found = []
    for store in reader.blueprints():
        layout = Layout()
        for chunk in reader.stream(store=store):
            _read(layout, chunk.entity_path, chunk.to_record_batch())
        found.append(layout)
    return found


def _read(layout: Layout, entity: str, batch: Any) -> None:
    names = [n for n in batch.schema.names if ":" in n]  # components, not the time columns
    columns = {name: batch.column(name).to_pylist() for name in names}
    parts = entity.strip("/").split("/")
    if "ViewBlueprint:class_identifier" in columns:
        layout.kinds[parts[1]] = columns["ViewBlueprint:class_identifier"][-1][0]
    if "SpatialInformation:target_frame" in columns:
        layout.target_frames[parts[1]] = columns["SpatialInformation:target_frame"][-1][0]
    if "VisualBounds2D:range" in columns:
        layout.y_ranges[parts[1]] = tuple(columns["VisualBounds2D:range"][-1][0]["y_range"])
    match = OVERRIDE.match(entity)
    for name, rows in columns.items():
        if match and (name.endswith(":colors") or name.endswith(":color")):
            for row in rows:
                layout.colours["/" + match.group(2)].update(row if isinstance(row, list) else [row])


def transform(path: Path, entity: str) -> dict[str, Any]:
    """The last value of each Transform3D field logged at `entity`."""
    from rerun.chunk import RrdReader

    fields: dict[str, Any] = {}
    for chunk in RrdReader(str(path)).stream():
        if chunk.entity_path == entity:
            batch = chunk.to_record_batch()
            for name in batch.schema.names:
                if name.startswith("Transform3D:"):
                    fields[name.split(":", 1)[1]] = batch.column(name).to_pylist()[-1]
    return fields


def logged_entities(path: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {chunk.entity_path for chunk in RrdReader(str(path)).stream()}


def packed(rgb: tuple[int, int, int]) -> int:
    """A colour as Rerun stores it: 0xRRGGBBAA, opaque."""
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | 0xFF


def test_every_2d_view_draws_y_up(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    positions = record(path)
    found = layouts(path)
    assert found, "the recording carries its layout"
    for layout in found:
        views_2d = [v for v, kind in layout.kinds.items() if kind == "2D"]
        assert views_2d
        for view in views_2d:
            assert layout.target_frames.get(view) == MAP_FRAME
    # The frame the map is drawn in is the world mirrored in y: a 2D view draws its own
    # +y downward, so the world's +y goes up.
    frame = transform(path, "/" + MAP_FRAME_ENTITY)
    assert frame["child_frame"] == [MAP_FRAME]
    assert frame["parent_frame"] == [ROOT_FRAME]
    to_root = np.asarray(frame["mat3x3"][0], dtype=float).reshape(3, 3).T  # column-major
    to_map = np.linalg.inv(to_root)
    np.testing.assert_allclose(to_map @ [0.0, 1.0, 0.0], [0.0, -1.0, 0.0])
    np.testing.assert_allclose(to_map @ [1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    # The map framed at the end holds every position, in the mirrored frame.
    framed = [r for layout in found for r in layout.y_ranges.values()]
    assert framed
    ys = [y for _, y in positions]
    for low, high in framed:
        assert low <= -max(ys)
        assert -min(ys) <= high


def test_each_robot_has_one_colour_in_every_view_never_the_bounds(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    record(path)
    colours = {rid: packed(rgb) for rid, rgb in robot_colours(IDS).items()}
    assert len(set(colours.values())) == len(IDS)
    logged = logged_entities(path)
    for layout in layouts(path):
        bounds = set().union(*(c for e, c in layout.colours.items() if e.startswith("/bounds/")))
        assert bounds, "the bounds are drawn in a colour of their own"
        assert not bounds & set(colours.values())
        for rid in IDS:
            base = f"/robots/{rid}/"
            drawn = {e for e in logged if e.startswith(base) and e[len(base) :] not in UNCOLOURED}
            assert len(drawn) >= 8, drawn  # pose, heading, trail, series, ...
            missing = drawn - layout.colours.keys()
            assert not missing, f"{rid}: drawn without its colour: {sorted(missing)}"
            for entity in drawn:
                assert layout.colours[entity] == {colours[rid]}, entity
