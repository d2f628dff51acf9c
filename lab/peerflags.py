"""A robot's flags as the leadership tests build them: valid, in formation, following r1
(the leader navigating), with any field overridden."""

from __future__ import annotations

from typing import Any

from phalanx.core.states import State
from phalanx.wire.messages import RobotFlags


def flags(rid: str, t_s: float = 10.0, **kw: Any) -> RobotFlags:
    """Robot `rid`'s flags stamped `t_s`, with the fields in `kw` instead."""
    base: dict[str, Any] = {
        "robot_id": rid,
        "seq": 1,
        "stamp_s": t_s,
        "fsm_state": State.NAVIGATE if rid == "r1" else State.FORMATION_TRACK,
        "formation_leader_id": "r1",
        "clear": True,
    }
    return RobotFlags(**{**base, **kw})
