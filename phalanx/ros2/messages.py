"""phalanx's values as ROS 2 messages (the classes of `rosbags`' type store), and back
for what the bridge takes in: the conventions REP-103 and REP-105 ask for, one place
for the bridge and the export.

Poses are planar: z = 0, the heading a rotation about z (quaternion `(0, 0, sin(t/2),
cos(t/2))`). A pose's covariance, when the robot publishes one (x, y, heading), fills
the x, y and yaw rows of the 6 x 6 matrix, the rest zero. Stamps are the fleet's clock
(sim time from 0 s in lockstep and in process, Unix time in real time).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from phalanx.core.config import WorldConfig
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.robot_params import SonarParams
from phalanx.ros2.names import robot_frame
from phalanx.ros2.typestore import Distro, store

# Indices into a 6 x 6 row-major covariance (x, y, z, roll, pitch, yaw) of the upper
# triangle a robot publishes: xx, xy, x-yaw, yy, y-yaw, yaw-yaw.
_COV_INDICES = ((0, 0), (0, 1), (0, 5), (1, 1), (1, 5), (5, 5))
_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
SLOT_COLOUR = (0.2, 0.6, 1.0, 0.4)
OBSTACLE_COLOUR = (0.5, 0.5, 0.5, 0.9)
_HEIGHT_M = 0.3  # how tall an obstacle and a slot are drawn


class RosMessages:
    """Builds ROS 2 messages of one distribution's definitions."""

    def __init__(self, distro: Distro = "jazzy") -> None:
        self._types = store(distro).types

    def _new(self, ros_type: str, **fields: Any) -> Any:
        return self._types[ros_type](**fields)

    def header(self, t_s: float, frame_id: str) -> Any:
        """std_msgs/Header at `t_s` (s) in `frame_id`."""
        nanos = round(t_s * 1e9)
        stamp = self._new("builtin_interfaces/msg/Time", sec=nanos // 10**9, nanosec=nanos % 10**9)
        return self._new("std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)

    def _vector(self, x: float, y: float, z: float, ros_type: str) -> Any:
        return self._new(ros_type, x=x, y=y, z=z)

    def _rotation(self, theta_rad: float) -> Any:
        half = 0.5 * theta_rad
        return self._new(
            "geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)
        )

    def _pose(self, pose: Pose2D) -> Any:
        position = self._vector(pose.x_m, pose.y_m, 0.0, "geometry_msgs/msg/Point")
        return self._new(
            "geometry_msgs/msg/Pose", position=position, orientation=self._rotation(pose.theta_rad)
        )

    def twist(self, twist: Twist2D) -> Any:
        """geometry_msgs/Twist: forward speed (m/s) and yaw rate (rad/s)."""
        return self._new(
            "geometry_msgs/msg/Twist",
            linear=self._vector(twist.v_mps, 0.0, 0.0, "geometry_msgs/msg/Vector3"),
            angular=self._vector(0.0, 0.0, twist.omega_radps, "geometry_msgs/msg/Vector3"),
        )

    def odometry(
        self, t_s: float, *, frame_id: str, child_frame_id: str, pose: Pose2D, twist: Twist2D,
        cov: Sequence[float] = (),
    ) -> Any:  # fmt: skip
        """nav_msgs/Odometry: `pose` in `frame_id`, `twist` in the robot's own frame
        (`child_frame_id`), `cov` the pose's (xx, xy, xt, yy, yt, tt) or empty.
        """
        covariance = np.zeros(36)
        for (row, col), value in zip(_COV_INDICES, cov, strict=False):
            covariance[6 * row + col] = covariance[6 * col + row] = value
        return self._new(
            "nav_msgs/msg/Odometry",
            header=self.header(t_s, frame_id),
            child_frame_id=child_frame_id,
            pose=self._new(
                "geometry_msgs/msg/PoseWithCovariance", pose=self._pose(pose), covariance=covariance
            ),
            twist=self._new(
                "geometry_msgs/msg/TwistWithCovariance",
                twist=self.twist(twist),
                covariance=np.zeros(36),
            ),
        )

    def text(self, value: str) -> Any:
        """std_msgs/String."""
        return self._new("std_msgs/msg/String", data=value)

    def transforms(self, t_s: float, links: Iterable[tuple[str, str, Pose2D]]) -> Any:
        """tf2_msgs/TFMessage: for each (parent, child, pose) the child frame's pose in its
        parent's at `t_s`.
        """
        stamped = [
            self._new(
                "geometry_msgs/msg/TransformStamped",
                header=self.header(t_s, parent),
                child_frame_id=child,
                transform=self._new(
                    "geometry_msgs/msg/Transform",
                    translation=self._vector(pose.x_m, pose.y_m, 0.0, "geometry_msgs/msg/Vector3"),
                    rotation=self._rotation(pose.theta_rad),
                ),
            )
            for parent, child, pose in links
        ]
        return self._new("tf2_msgs/msg/TFMessage", transforms=stamped)

    def sonar_cloud(
        self, t_s: float, frame_id: str, sonar: SonarParams, ranges_m: Sequence[float]
    ) -> Any:
        """sensor_msgs/PointCloud2 of a sonar ring's echoes in the robot's frame: one point
        (x, y, z float32) per transducer whose range is within the sonar's, where the echo
        came from along its axis.
        """
        points = [
            (unit.x_m + r * math.cos(h), unit.y_m + r * math.sin(h), 0.0)
            for unit, r in zip(sonar.units, ranges_m, strict=False)
            if sonar.min_range_m <= r < sonar.max_range_m
            for h in (math.radians(unit.heading_deg),)
        ]
        data = np.asarray(points, dtype="<f4").reshape(-1, 3).view(np.uint8).reshape(-1)
        fields = [
            self._new(
                "sensor_msgs/msg/PointField", name=n, offset=4 * i, datatype=_FLOAT32, count=1
            )
            for i, n in enumerate("xyz")
        ]
        return self._new(
            "sensor_msgs/msg/PointCloud2",
            header=self.header(t_s, frame_id),
            height=1, width=len(points), fields=fields, is_bigendian=False, point_step=12,
            row_step=12 * len(points), data=data, is_dense=True,
        )  # fmt: skip

    def markers(
        self, t_s: float, frame_id: str, *, slots: Sequence[tuple[float, float]], radius_m: float,
        world: WorldConfig,
    ) -> Any:  # fmt: skip
        """visualization_msgs/MarkerArray: a disc per formation slot (namespace `slots`),
        a cylinder per round obstacle (`obstacles`) and an outline per polygon (`walls`),
        all in `frame_id`.
        """
        header = self.header(t_s, frame_id)
        out = [
            self._disc(header, "slots", i, xy, radius_m, SLOT_COLOUR) for i, xy in enumerate(slots)
        ]
        out += [
            self._disc(header, "obstacles", i, (c.x_m, c.y_m), c.radius_m, OBSTACLE_COLOUR)
            for i, c in enumerate(world.circles)
        ]
        out += [self._outline(header, i, p.vertices_m) for i, p in enumerate(world.polygons)]
        return self._new("visualization_msgs/msg/MarkerArray", markers=out)

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
