"""Every Zenoh key phalanx uses, built in one place.

All are fleet-scoped, under `phalanx/<fleet>/`:

robot/<id>/state    RobotState, every control step (to the robots that may track it)
robot/<id>/flags    RobotFlags: leadership and deadlock flags, to every robot
robot/<id>/sense    SenseFrame from the world (sim driver)
robot/<id>/cmd      VelocityCommand to the world (sim driver)
robot/<id>/event    AgentEvent (behaviour transitions)
robot/<id>/report   AgentReport at the end of a run
robot/<id>/scan     ScanMessage: a navigating robot's sonar reading, for the fleet's map
robot/<id>/fix      PoseFixMessage: an absolute pose fix (`phalanx mocap`, or the world
                    simulating motion capture for robots on drivers)
robot/<id>/truth    TruthMessage: where a simulator says the robot is (the robot's agent,
                    from its driver: AMRISim), for the run's record
robot/<id>/relative RelativeFixMessage: another robot seen by this one's camera (the world
                    simulating it for robots on drivers)
robot/<id>/operator OperatorCommand: what an operator asks of the robot that leads (a
                    twist, a goal), from `phalanx ros2` (ROS 2's cmd_vel and goal_pose)
leader              LeaderAnnouncement (who leads, under which epoch)
alive/<id>          liveliness token of each process
status/<id>         queryable: a process's counters as JSON
host/<name>/...     a host daemon's liveliness, queryables and log lines
"""

from __future__ import annotations

import re

from phalanx.core.errors import TransportError

_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def _name(value: str, what: str) -> str:
    if not _NAME.match(value):
        raise TransportError(f"{what} {value!r}: use 1-64 letters, digits, '_' or '-'")
    return value


def robot_key(fleet: str, robot_id: str, topic: str) -> str:
    """`phalanx/<fleet>/robot/<id>/<topic>`."""
    return f"phalanx/{_name(fleet, 'fleet')}/robot/{_name(robot_id, 'robot id')}/{topic}"


def robots_key(fleet: str, topic: str) -> str:
    """Every robot's `topic`: `phalanx/<fleet>/robot/*/<topic>`."""
    return f"phalanx/{_name(fleet, 'fleet')}/robot/*/{topic}"


def alive_key(fleet: str, process_id: str) -> str:
    """Liveliness token key of a process."""
    return f"phalanx/{_name(fleet, 'fleet')}/alive/{_name(process_id, 'process id')}"


def alive_pattern(fleet: str) -> str:
    """Every process's liveliness token: `phalanx/<fleet>/alive/*`."""
    return f"phalanx/{_name(fleet, 'fleet')}/alive/*"


def status_key(fleet: str, process_id: str) -> str:
    """Status queryable of a process."""
    return f"phalanx/{_name(fleet, 'fleet')}/status/{_name(process_id, 'process id')}"


def statuses_key(fleet: str) -> str:
    """Every process's status queryable: `phalanx/<fleet>/status/*`."""
    return f"phalanx/{_name(fleet, 'fleet')}/status/*"


def robot_of(key: str) -> str:
    """The robot id in a `phalanx/<fleet>/robot/<id>/...` key ("" for any other key)."""
    parts = key.split("/")
    return parts[3] if len(parts) > 4 and parts[2] == "robot" else ""


def leader_key(fleet: str) -> str:
    """`phalanx/<fleet>/leader`, where a robot that takes the lead announces it."""
    return f"phalanx/{_name(fleet, 'fleet')}/leader"


def host_key(fleet: str, host: str, topic: str) -> str:
    """`phalanx/<fleet>/host/<host>/<topic>`."""
    return f"phalanx/{fleet}/host/{host}/{topic}"


def hosts_key(fleet: str, topic: str) -> str:
    """Every host's `topic`: `phalanx/<fleet>/host/*/<topic>`."""
    return f"phalanx/{fleet}/host/*/{topic}"


def log_key(fleet: str, host: str, child: str) -> str:
    """Where a host publishes a child's output."""
    return host_key(fleet, host, f"log/{child}")


def logs_key(fleet: str) -> str:
    """Every host's children's output."""
    return f"phalanx/{fleet}/host/*/log/*"


def host_of(key: str) -> str:
    """The host name in a `phalanx/<fleet>/host/<name>/...` key ("" for any other key)."""
    parts = key.split("/")
    return parts[3] if len(parts) > 3 and parts[2] == "host" else ""
