"""The ROS 2 tier: what the bridge publishes and the export writes, read back by software
nobody here wrote (rosbags' CDR and bag reader, the MCAP library's reader and ROS 2
decoder, ROBOTIS' zenoh-ros2-sdk), with rmw_zenoh's design document as the reference
for keys and tokens.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.robot_params import RobotParams

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"

# ROS 2's own definitions (common_interfaces, rcl_interfaces) of the messages the
# independent SDK is asked to compute hashes of and to decode: it reads them as .msg files.
MSG_DEFINITIONS = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/String": "string data\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Twist": "Vector3  linear\nVector3  angular\n",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n"
    ),
}


@pytest.fixture(scope="session")
def wedge() -> Scenario:
    """The paper's wedge: three robots, a V-shaped wall."""
    return load_scenario(WEDGE)


@pytest.fixture(scope="session")
def p3dx() -> RobotParams:
    """The P3DX's parameter file (16 sonars)."""
    return load_robot("p3dx")


@pytest.fixture(scope="session")
def msg_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`MSG_DEFINITIONS` as a folder of .msg files, `<package>/msg/<Name>.msg`."""
    root = tmp_path_factory.mktemp("msgs")
    for ros_type, text in MSG_DEFINITIONS.items():
        path = root / f"{ros_type}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return root


@pytest.fixture
def sdk_registry(msg_folder: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """The SDK's message registry reading `msg_folder` (it would fetch definitions from
    the network otherwise); its shared session closed after the test.
    """
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    monkeypatch.setattr(
        message_registry, "_registry", message_registry.MessageRegistry(str(msg_folder))
    )
    try:
        yield
    finally:
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
