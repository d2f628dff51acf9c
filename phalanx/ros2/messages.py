"""phalanx's values as ROS 2 messages (the classes of `rosbags`' type store), and back
for what the bridge takes in: the conventions REP-103 and REP-105 ask for, one place
for the bridge and the export.

Every message is built blank and its values filled in (`fill_*`): the export builds a
new one each time; the bridge builds each robot's once (`RobotMessages`, and the
markers' `FleetMarkers`) and fills the same objects every round, as it serialises each
before the next fill. The odometry, the command and the sonar cloud, whose strings never
change, it writes from CDR templates (`phalanx.ros2.typestore.CdrTemplate`) with the
same values (`odometry_values` for `ODOMETRY_FIELDS`, ...).

Poses are planar: z = 0, the heading a rotation about z (quaternion `(0, 0, sin(t/2),
cos(t/2))`). A pose's covariance, when the robot publishes one (x, y, heading), fills
the x, y and yaw rows of the 6 x 6 matrix, the rest zero. Stamps are the fleet's clock
(sim time from 0 s in lockstep and in process, Unix time in real time).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from phalanx.core.config import WorldConfig
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.robot_params import SonarParams
from phalanx.ros2.names import robot_frame
from phalanx.ros2.typestore import CdrTemplate, Distro, store

# Indices into a 6 x 6 row-major covariance (x, y, z, roll, pitch, yaw) of the upper
# triangle a robot publishes: xx, xy, x-yaw, yy, y-yaw, yaw-yaw.
_COV_INDICES = ((0, 0), (0, 1), (0, 5), (1, 1), (1, 5), (5, 5))
_COV_CELLS = tuple((6 * row + col, 6 * col + row) for row, col in _COV_INDICES)
_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
_POINT_BYTES = 12  # x, y, z
SLOT_COLOUR = (0.2, 0.6, 1.0, 0.4)
OBSTACLE_COLOUR = (0.5, 0.5, 0.5, 0.9)
_HEIGHT_M = 0.3  # how tall an obstacle and a slot are drawn
_ORIGIN = Pose2D(0.0, 0.0, 0.0)
_STILL = Twist2D(0.0, 0.0)


class RosMessages:
    """Builds ROS 2 messages of one distribution's definitions."""

    def __init__(self, distro: Distro = "jazzy") -> None:
        self.distro: Distro = distro
        self._types = store(distro).types

    def _new(self, ros_type: str, **fields: Any) -> Any:
        return self._types[ros_type](**fields)

    def header(self, t_s: float, frame_id: str) -> Any:
        """std_msgs/Header at `t_s` (s) in `frame_id`."""
        stamp = self._new("builtin_interfaces/msg/Time", sec=0, nanosec=0)
        header = self._new("std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)
        fill_header(header, t_s)
        return header

    def _vector(self, x: float, y: float, z: float, ros_type: str) -> Any:
        return self._new(ros_type, x=x, y=y, z=z)

    def _rotation(self, theta_rad: float) -> Any:
        rotation = self._new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)
        _fill_rotation(rotation, theta_rad)
        return rotation

    def _pose(self, pose: Pose2D) -> Any:
        position = self._vector(pose.x_m, pose.y_m, 0.0, "geometry_msgs/msg/Point")
        return self._new(
            "geometry_msgs/msg/Pose", position=position, orientation=self._rotation(pose.theta_rad)
        )

    def twist(self, twist: Twist2D) -> Any:
        """geometry_msgs/Twist: forward speed (m/s) and yaw rate (rad/s)."""
        message = self._new(
            "geometry_msgs/msg/Twist",
            linear=self._vector(0.0, 0.0, 0.0, "geometry_msgs/msg/Vector3"),
            angular=self._vector(0.0, 0.0, 0.0, "geometry_msgs/msg/Vector3"),
        )
        fill_twist(message, twist)
        return message

    def odometry(
        self, t_s: float, *, frame_id: str, child_frame_id: str, pose: Pose2D, twist: Twist2D,
        cov: Sequence[float] = (),
    ) -> Any:  # fmt: skip
        """nav_msgs/Odometry: `pose` in `frame_id`, `twist` in the robot's own frame
        (`child_frame_id`), `cov` the pose's (xx, xy, xt, yy, yt, tt) or empty.
        """
        message = self._new(
            "nav_msgs/msg/Odometry",
            header=self.header(t_s, frame_id),
            child_frame_id=child_frame_id,
            pose=self._new(
                "geometry_msgs/msg/PoseWithCovariance", pose=self._pose(_ORIGIN),
                covariance=np.zeros(36),
            ),
            twist=self._new(
                "geometry_msgs/msg/TwistWithCovariance", twist=self.twist(_STILL),
                covariance=np.zeros(36),
            ),
        )  # fmt: skip
        fill_odometry(message, t_s, pose=pose, twist=twist, cov=cov)
        return message

    def text(self, value: str) -> Any:
        """std_msgs/String."""
        return self._new("std_msgs/msg/String", data=value)

    def transforms(self, t_s: float, links: Iterable[tuple[str, str, Pose2D]]) -> Any:
        """tf2_msgs/TFMessage: for each (parent, child, pose) the child frame's pose in its
        parent's at `t_s`.
        """
        stamped = [self.link(parent, child) for parent, child, _ in links]
        for transform, (_, _, pose) in zip(stamped, links, strict=True):
            fill_link(transform, t_s, pose)
        return self._new("tf2_msgs/msg/TFMessage", transforms=stamped)

    def link(self, parent: str, child: str) -> Any:
        """geometry_msgs/TransformStamped of frame `child` in `parent`, blank (the
        identity at 0 s): `fill_link` gives it its stamp and pose.
        """
        return self._new(
            "geometry_msgs/msg/TransformStamped",
            header=self.header(0.0, parent),
            child_frame_id=child,
            transform=self._new(
                "geometry_msgs/msg/Transform",
                translation=self._vector(0.0, 0.0, 0.0, "geometry_msgs/msg/Vector3"),
                rotation=self._rotation(0.0),
            ),
        )

    def sonar_cloud(
        self, t_s: float, frame_id: str, sonar: SonarParams, ranges_m: Sequence[float]
    ) -> Any:
        """sensor_msgs/PointCloud2 of a sonar ring's echoes in the robot's frame: one point
        (x, y, z float32) per transducer whose range is within the sonar's, where the echo
        came from along its axis.
        """
        cloud = self.blank_cloud(frame_id)
        fill_cloud(cloud, t_s, SonarRing.of(sonar), ranges_m)
        return cloud

    def blank_cloud(self, frame_id: str) -> Any:
        """sensor_msgs/PointCloud2 of x, y, z float32 points in `frame_id`, none yet."""
        fields = [
            self._new(
                "sensor_msgs/msg/PointField", name=n, offset=4 * i, datatype=_FLOAT32, count=1
            )
            for i, n in enumerate("xyz")
        ]
        return self._new(
            "sensor_msgs/msg/PointCloud2",
            header=self.header(0.0, frame_id),
            height=1, width=0, fields=fields, is_bigendian=False, point_step=_POINT_BYTES,
            row_step=0, data=np.zeros(0, dtype=np.uint8), is_dense=True,
        )  # fmt: skip

    def markers(
        self, t_s: float, frame_id: str, *, slots: Sequence[tuple[float, float]], radius_m: float,
        world: WorldConfig,
    ) -> Any:  # fmt: skip
        """visualization_msgs/MarkerArray: a disc per formation slot (namespace `slots`),
        a cylinder per round obstacle (`obstacles`) and an outline per polygon (`walls`),
        all in `frame_id`.
        """
        board = FleetMarkers(self, frame_id, slots=len(slots), radius_m=radius_m, world=world)
        return board.fill(t_s, slots)

    def marker_array(
        self, header: Any, *, slots: int, radius_m: float, world: WorldConfig
    ) -> tuple[Any, list[Any]]:
        """A MarkerArray as `markers` draws it, all its markers sharing `header`, with
        `slots` slots at the origin; and those slots' markers, to move.
        """
        moving = [
            self._disc(header, "slots", i, (0.0, 0.0), radius_m, SLOT_COLOUR) for i in range(slots)
        ]
        still = [
            self._disc(header, "obstacles", i, (c.x_m, c.y_m), c.radius_m, OBSTACLE_COLOUR)
            for i, c in enumerate(world.circles)
        ]
        still += [self._outline(header, i, p.vertices_m) for i, p in enumerate(world.polygons)]
        array = self._new("visualization_msgs/msg/MarkerArray", markers=[*moving, *still])
        return array, moving

    def _disc(
        self, header: Any, ns: str, index: int, xy: tuple[float, float], radius_m: float,
        colour: tuple[float, float, float, float],
    ) -> Any:  # fmt: skip
        pose = self._pose(Pose2D(xy[0], xy[1], 0.0))
        scale = self._vector(2 * radius_m, 2 * radius_m, _HEIGHT_M, "geometry_msgs/msg/Vector3")
        return self._marker(header, ns, index, 3, pose, scale, colour, [])  # CYLINDER

    def _outline(self, header: Any, index: int, vertices: Sequence[tuple[float, float]]) -> Any:
        points = [self._vector(x, y, 0.0, "geometry_msgs/msg/Point") for x, y in vertices]
        points.append(points[0])
        scale = self._vector(0.05, 0.0, 0.0, "geometry_msgs/msg/Vector3")  # the line's width
        pose = self._pose(Pose2D(0.0, 0.0, 0.0))
        return self._marker(header, "walls", index, 4, pose, scale, OBSTACLE_COLOUR, points)

    def _marker(
        self, header: Any, ns: str, index: int, kind: int, pose: Any, scale: Any,
        colour: tuple[float, float, float, float], points: list[Any],
    ) -> Any:  # fmt: skip
        r, g, b, a = colour
        empty = np.zeros(0, dtype=np.uint8)
        return self._new(
            "visualization_msgs/msg/Marker",
            header=header, ns=ns, id=index, type=kind, action=0, pose=pose, scale=scale,
            color=self._new("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a),
            lifetime=self._new("builtin_interfaces/msg/Duration", sec=0, nanosec=0),
            frame_locked=False, points=points, colors=[], texture_resource="",
            texture=self._new(
                "sensor_msgs/msg/CompressedImage", header=header, format="", data=empty
            ),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=self._new("visualization_msgs/msg/MeshFile", filename="", data=empty),
            mesh_use_embedded_materials=False,
        )  # fmt: skip


def stamp_values(t_s: float) -> tuple[int, int]:
    """builtin_interfaces/Time of `t_s` (s): (sec, nanosec)."""
    sec, nanosec = divmod(round(t_s * 1e9), 10**9)
    return sec, nanosec


def fill_header(header: Any, t_s: float) -> None:
    """Stamp std_msgs/Header `header` with `t_s` (s)."""
    header.stamp.sec, header.stamp.nanosec = stamp_values(t_s)


def _fill_rotation(rotation: Any, theta_rad: float) -> None:
    half = 0.5 * theta_rad
    rotation.z, rotation.w = math.sin(half), math.cos(half)


# The fields of a geometry_msgs/Twist and a nav_msgs/Odometry that change (the rest stay
# as built: zero, the frames' names), in the order of `twist_values`, `odometry_values`.
TWIST_FIELDS = ("linear.x", "angular.z")
ODOMETRY_FIELDS = (
    "header.stamp.sec", "header.stamp.nanosec", "pose.pose.position.x",
    "pose.pose.position.y", "pose.pose.orientation.z", "pose.pose.orientation.w",
    "pose.covariance", *(f"twist.twist.{field}" for field in TWIST_FIELDS),
)  # fmt: skip


def twist_values(twist: Twist2D) -> tuple[float, float]:
    """`TWIST_FIELDS`: forward speed (m/s) and yaw rate (rad/s)."""
    return twist.v_mps, twist.omega_radps


def odometry_values(
    t_s: float, *, pose: Pose2D, twist: Twist2D, cov: Sequence[float] = ()
) -> tuple[Any, ...]:
    """`ODOMETRY_FIELDS` at `t_s`: `pose`, `twist`, `cov` the pose's (xx, xy, xt, yy, yt,
    tt) or empty (zeros).
    """
    covariance = [0.0] * 36
    for (at, mirror), value in zip(_COV_CELLS, cov, strict=False):
        covariance[at] = covariance[mirror] = value
    half = 0.5 * pose.theta_rad
    return (
        *stamp_values(t_s), pose.x_m, pose.y_m, math.sin(half), math.cos(half), covariance,
        *twist_values(twist),
    )  # fmt: skip


def fill_fields(message: Any, fields: Sequence[str], values: Sequence[Any]) -> None:
    """Set each of `fields` (dotted paths) of `message` to its value in `values`."""
    for field, value in zip(fields, values, strict=True):
        *parents, name = field.split(".")
        owner = message
        for part in parents:
            owner = getattr(owner, part)
        current = getattr(owner, name)
        if isinstance(current, np.ndarray):
            current[:] = value
        else:
            setattr(owner, name, value)


def fill_twist(message: Any, twist: Twist2D) -> None:
    """geometry_msgs/Twist `message`: forward speed (m/s) and yaw rate (rad/s)."""
    fill_fields(message, TWIST_FIELDS, twist_values(twist))


def fill_odometry(
    message: Any, t_s: float, *, pose: Pose2D, twist: Twist2D, cov: Sequence[float] = ()
) -> None:
    """nav_msgs/Odometry `message`, as `odometry_values`."""
    fill_fields(message, ODOMETRY_FIELDS, odometry_values(t_s, pose=pose, twist=twist, cov=cov))


def fill_link(message: Any, t_s: float, pose: Pose2D) -> None:
    """geometry_msgs/TransformStamped `message`: its child frame at `pose` at `t_s`."""
    fill_header(message.header, t_s)
    transform = message.transform
    transform.translation.x, transform.translation.y = pose.x_m, pose.y_m
    _fill_rotation(transform.rotation, pose.theta_rad)


@dataclass(frozen=True)
class SonarRing:
    """A sonar ring's transducers as the point cloud needs them: each one's position (m)
    and axis (cos, sin) in the robot's frame, and the ranges (m) that are echoes.
    """

    units: tuple[tuple[float, float, float, float], ...]
    min_range_m: float
    max_range_m: float

    @classmethod
    def of(cls, sonar: SonarParams) -> SonarRing:
        """The ring of parameter file section `sonar`."""
        axes = [(u.x_m, u.y_m, math.radians(u.heading_deg)) for u in sonar.units]
        units = tuple((x, y, math.cos(h), math.sin(h)) for x, y, h in axes)
        return cls(units, sonar.min_range_m, sonar.max_range_m)

    def points(self, ranges_m: Sequence[float]) -> list[float]:
        """x, y, z (m) of each echo in `ranges_m` (one range per transducer, in order)."""
        out: list[float] = []
        low, high = self.min_range_m, self.max_range_m
        for (x, y, cos, sin), r in zip(self.units, ranges_m, strict=False):
            if low <= r < high:
                out += (x + r * cos, y + r * sin, 0.0)
        return out


# The fields of a point cloud (of `blank_cloud`) that change besides its `data`.
CLOUD_FIELDS = ("header.stamp.sec", "header.stamp.nanosec", "width", "row_step")


def cloud_values(
    t_s: float, ring: SonarRing, ranges_m: Sequence[float]
) -> tuple[tuple[int, ...], bytes]:
    """`CLOUD_FIELDS` and `data` of the point cloud of `ring`'s echoes among `ranges_m`
    at `t_s` (x, y, z little-endian float32).
    """
    xyz = ring.points(ranges_m)
    points = len(xyz) // 3
    data = struct.pack(f"<{len(xyz)}f", *xyz)
    return (*stamp_values(t_s), points, _POINT_BYTES * points), data


def fill_cloud(message: Any, t_s: float, ring: SonarRing, ranges_m: Sequence[float]) -> None:
    """sensor_msgs/PointCloud2 `message` (of `blank_cloud`), as `cloud_values`."""
    values, data = cloud_values(t_s, ring, ranges_m)
    fill_fields(message, CLOUD_FIELDS, values)
    message.data = np.frombuffer(data, dtype=np.uint8)


class RobotMessages:
    """One robot's messages of a bridge round, built once: its odometry (in
    `map_frame`), command and sonar cloud (in its `base_link`) as CDR, from templates of
    their blank messages; its behaviour state and TF link as messages, each method
    returning the same object, refilled.
    """

    def __init__(
        self, msgs: RosMessages, robot_id: str, *, map_frame: str, sonar: SonarParams
    ) -> None:
        base = robot_frame(robot_id)
        odom = msgs.odometry(
            0.0, frame_id=map_frame, child_frame_id=base, pose=_ORIGIN, twist=_STILL
        )
        self._odom = CdrTemplate(odom, "nav_msgs/msg/Odometry", ODOMETRY_FIELDS, msgs.distro)
        twist = msgs.twist(_STILL)
        self._twist = CdrTemplate(twist, "geometry_msgs/msg/Twist", TWIST_FIELDS, msgs.distro)
        self._text = msgs.text("")
        self._link = msgs.link(map_frame, base)
        self._cloud = CdrTemplate(
            msgs.blank_cloud(base), "sensor_msgs/msg/PointCloud2", CLOUD_FIELDS, msgs.distro,
            tail="data",
        )  # fmt: skip
        self._ring = SonarRing.of(sonar)

    def odometry_cdr(
        self, t_s: float, *, pose: Pose2D, twist: Twist2D, cov: Sequence[float] = ()
    ) -> bytearray:
        """nav_msgs/Odometry as CDR, as `RosMessages.odometry` builds it."""
        return self._odom(odometry_values(t_s, pose=pose, twist=twist, cov=cov))

    def twist_cdr(self, twist: Twist2D) -> bytearray:
        """geometry_msgs/Twist as CDR, as `RosMessages.twist` builds it."""
        return self._twist(twist_values(twist))

    def text(self, value: str) -> Any:
        """std_msgs/String."""
        self._text.data = value
        return self._text

    def link(self, t_s: float, pose: Pose2D) -> Any:
        """geometry_msgs/TransformStamped: its `base_link` at `pose` in the map frame."""
        fill_link(self._link, t_s, pose)
        return self._link

    def sonar_cdr(self, t_s: float, ranges_m: Sequence[float]) -> bytearray:
        """sensor_msgs/PointCloud2 as CDR, as `RosMessages.sonar_cloud` builds it."""
        values, data = cloud_values(t_s, self._ring, ranges_m)
        return self._cloud(values, data)


class FleetMarkers:
    """The fleet's markers (`RosMessages.markers`), built once: the obstacles and walls
    do not move; each fill stamps them and moves the slots.
    """

    def __init__(
        self, msgs: RosMessages, frame_id: str, *, slots: int, radius_m: float, world: WorldConfig
    ) -> None:
        self._header = msgs.header(0.0, frame_id)
        self._array, self._slots = msgs.marker_array(
            self._header, slots=slots, radius_m=radius_m, world=world
        )

    def fill(self, t_s: float, slots: Sequence[tuple[float, float]]) -> Any:
        """The MarkerArray at `t_s`, the slots at `slots` (x, y in m; one per slot)."""
        fill_header(self._header, t_s)
        for marker, (x_m, y_m) in zip(self._slots, slots, strict=True):
            marker.pose.position.x, marker.pose.position.y = x_m, y_m
        return self._array


def planar_twist(message: Any) -> Twist2D:
    """A geometry_msgs/Twist as the robot drives it: forward speed (linear x, m/s) and yaw
    rate (angular z, rad/s); a differential drive has no other (the rest is ignored).
    """
    return Twist2D(float(message.linear.x), float(message.angular.z))


def stamped_position(message: Any) -> tuple[str, Vec2]:
    """A geometry_msgs/PoseStamped's frame and its position in it (m; the orientation
    and z are ignored: a goal is a place to get to).
    """
    position = message.pose.position
    return str(message.header.frame_id), Vec2(float(position.x), float(position.y))


def sonar_mounts(robot_ids: Iterable[str], sonar: SonarParams) -> list[tuple[str, str, Pose2D]]:
    """Every robot's sonar mounts as TF links (`r1/base_link`, `r1/sonar_<i>`, the mount's
    pose in the robot's frame), transducers in the parameter file's order.
    """
    return [
        (
            robot_frame(rid),
            robot_frame(rid, f"sonar_{i}"),
            Pose2D(u.x_m, u.y_m, math.radians(u.heading_deg)),
        )
        for rid in robot_ids
        for i, u in enumerate(sonar.units)
    ]
