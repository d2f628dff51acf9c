"""A finished run as a rosbag2 bag in MCAP storage (`phalanx export RESULTS --mcap`,
`phalanx run --mcap`), which `ros2 bag play`, Foxglove and PlotJuggler open.

The bag holds the bridge's topics (`phalanx.ros2.topics`) with the run's own stamps (the
fleet clock: sim time from 0 s) as both the messages' header stamps and the bag's log
times. Per robot and control step: `odom` (the recorded pose and the twist it drove),
`cmd_vel_out` (what it commanded), and `state` when its behaviour state changed (and at
the first step); `/tf` once a step with every robot; with the run's scenario given,
`/tf_static` (the sonar mounts) at the first step and `markers` once a second of run
time: the formation's slots laid out from its root robot, the world's obstacles. A
results folder keeps no sonar readings, so the bag has no `sonar` topic.

Written with `rosbags`' rosbag2 writer (MCAP storage, bag version 9): the folder
`<out>` holds `<out name>.mcap` and `metadata.yaml`. It is written beside its place and
moved there whole.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.config import Ros2Config, Scenario, WorldConfig
from phalanx.core.errors import ConfigError
from phalanx.core.formation import Formation, scenario_formation
from phalanx.core.geometry import Twist2D
from phalanx.core.robot_params import RobotParams
from phalanx.core.runlog import RobotTrace, RunLog
from phalanx.core.scenarios import resolve_world
from phalanx.ros2.bridge import slot_positions
from phalanx.ros2.messages import RosMessages, sonar_mounts
from phalanx.ros2.names import TRANSIENT_LOCAL, Qos, robot_frame
from phalanx.ros2.topics import RosTopic, fleet_topics
from phalanx.ros2.typestore import store, to_cdr

BAG_NAME = "rosbag2"
MARKER_PERIOD_S = 1.0
FloatArray = npt.NDArray[np.float64]
Topics = Mapping[tuple[str, str], RosTopic]  # (kind, robot id) -> topic


class ExportError(ConfigError):
    """A results folder that cannot be exported (a file missing or not a run's)."""


@dataclass(frozen=True)
class RunTraces:
    """What a bag is written from: the steps' times (s) and every robot's trace."""

    t_s: FloatArray
    robots: Mapping[str, RobotTrace]

    @classmethod
    def from_log(cls, log: RunLog) -> RunTraces:
        """A run still in memory (`phalanx run --mcap`)."""
        return cls(np.asarray(log.t_s, dtype=float), dict(log.traces))

    @classmethod
    def from_folder(cls, folder: Path) -> RunTraces:
        """A results folder's `traces.npz` (ExportError if it has none)."""
        from phalanx.analysis.results import read_run_traces

        path = folder / "traces.npz"
        if not path.is_file():
            raise ExportError(
                f"{folder}: no traces.npz (a run writes it with its figures: run without "
                "--no-figures, or export with `phalanx run --mcap`)"
            )
        try:
            return cls(*read_run_traces(path))
        except (KeyError, ValueError, OSError) as exc:
            raise ExportError(f"{path}: not a run's traces ({exc})") from exc


def scenario_of_folder(folder: Path) -> str:
    """The scenario name a results folder's `metrics.json` records ("" if none)."""
    try:
        metrics = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return ""
    return str(metrics.get("scenario", "")) if isinstance(metrics, dict) else ""


@dataclass(frozen=True)
class Extras:
    """What the run's scenario adds to a bag: sonar mounts, slots and obstacles."""

    robot: RobotParams
    formation: Formation
    world: WorldConfig

    @classmethod
    def of(cls, scenario: Scenario, robot: RobotParams) -> Extras:
        """The extras of a run of `scenario` with robots of `robot`'s type."""
        return cls(robot, scenario_formation(scenario), resolve_world(scenario.world))


def write_bag(
    record: RunTraces, out: Path, *, cfg: Ros2Config, extras: Extras | None = None
) -> dict[str, int]:
    """Write `record` as a rosbag2 MCAP bag in folder `out` (replaced if there); how
    many messages each topic got.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    out = out.resolve()
    kinds = ("odom", "cmd_vel_out", "state", "tf", *(("tf_static", "markers") if extras else ()))
    topics = [t for t in fleet_topics(cfg, list(record.robots)) if t.kind in kinds]
    drafts = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        bag = drafts / out.name
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            connections = {(t.kind, t.robot_id): _connect(writer, t, cfg) for t in topics}
            counts: dict[str, int] = {t.name: 0 for t in topics}
            for topic, t_s, message in _messages(record, cfg, extras, topics):
                key = (topic.kind, topic.robot_id)
                writer.write(
                    connections[key], _ns(t_s), to_cdr(message, topic.ros_type, cfg.distro)
                )
                counts[topic.name] += 1
        if out.exists():
            shutil.rmtree(out)
        os.replace(bag, out)
    finally:
        shutil.rmtree(drafts, ignore_errors=True)
    return counts


def _ns(t_s: float) -> int:
    return round(t_s * 1e9)


def _connect(writer: Any, topic: RosTopic, cfg: Ros2Config) -> Any:
    return writer.add_connection(
        topic.name, topic.ros_type, typestore=store(cfg.distro),
        offered_qos_profiles=[_bag_qos(topic.qos)],
    )  # fmt: skip


def _bag_qos(qos: Qos) -> Any:
    """The QoS a bag records a topic as offered with (what `ros2 bag play` offers again)."""
    from rosbags.interfaces import (
        Qos as BagQos,
    )
    from rosbags.interfaces import (
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    durable = qos.durability == TRANSIENT_LOCAL
    return BagQos(
        history=QosHistory.KEEP_LAST, depth=qos.depth, reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL if durable else QosDurability.VOLATILE,
        deadline=QosTime(0, 0), lifespan=QosTime(0, 0), liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=QosTime(0, 0), avoid_ros_namespace_conventions=False,
    )  # fmt: skip


def _messages(
    record: RunTraces, cfg: Ros2Config, extras: Extras | None, topics: list[RosTopic]
) -> Iterator[tuple[RosTopic, float, Any]]:
    """Every message of the bag in time order: (topic, stamp in s, message)."""
    msgs = RosMessages(cfg.distro)
    by_kind: dict[tuple[str, str], RosTopic] = {(t.kind, t.robot_id): t for t in topics}
    if extras is not None and record.t_s.size:
        links = sonar_mounts(record.robots, extras.robot.sonar)
        yield (
            by_kind["tf_static", ""],
            float(record.t_s[0]),
            msgs.transforms(float(record.t_s[0]), links),
        )
    next_markers_s = -math.inf
    for k, t in enumerate(record.t_s.tolist()):
        yield from _step(record, cfg, msgs, by_kind, k, t)
        if extras is not None and t >= next_markers_s:
            next_markers_s = t + MARKER_PERIOD_S
            yield by_kind["markers", ""], t, _markers(msgs, record, cfg, extras, k, t)


def _step(
    record: RunTraces, cfg: Ros2Config, msgs: RosMessages, by_kind: Topics, k: int, t: float
) -> Iterator[tuple[RosTopic, float, Any]]:
    links = []
    for rid, robot in record.robots.items():
        pose = robot.pose(k)
        measured = Twist2D(float(robot.v_mps[k]), float(robot.omega_radps[k]))
        odom = msgs.odometry(
            t, frame_id=cfg.map_frame, child_frame_id=robot_frame(rid), pose=pose, twist=measured
        )
        yield by_kind["odom", rid], t, odom
        command = Twist2D(float(robot.cmd_v_mps[k]), float(robot.cmd_omega_radps[k]))
        yield by_kind["cmd_vel_out", rid], t, msgs.twist(command)
        if k == 0 or robot.states[k] != robot.states[k - 1]:
            yield by_kind["state", rid], t, msgs.text(robot.states[k])
        links.append((cfg.map_frame, robot_frame(rid), pose))
    yield by_kind["tf", ""], t, msgs.transforms(t, links)


def _markers(
    msgs: RosMessages, record: RunTraces, cfg: Ros2Config, extras: Extras, k: int, t: float
) -> Any:
    root = extras.formation.root
    slots = slot_positions(extras.formation.positions, root, record.robots[root].pose(k))
    return msgs.markers(
        t, cfg.map_frame, slots=slots, radius_m=extras.robot.radius_m, world=extras.world
    )
