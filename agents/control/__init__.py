"""Follower controllers: the paper's tracking (eq. 1-3) and ICR (eq. 7) laws, and ours."""

from __future__ import annotations

from phalanx.agents.control.common import FollowerController, FollowerInput
from phalanx.agents.control.ours import OursController
from phalanx.agents.control.paper import PaperIcr, PaperSwitching, PaperTracking
from phalanx.core.config import ControllerConfig

__all__ = [
    "FollowerController",
    "FollowerInput",
    "OursController",
    "PaperIcr",
    "PaperSwitching",
    "PaperTracking",
    "make_controller",
]


def make_controller(cfg: ControllerConfig) -> FollowerController:
    """The controller a scenario's `[controller]` table names."""
    match cfg.kind:
        case "tracking":
            return PaperTracking(k1=cfg.k1, k2=cfg.k2, h_m=cfg.h_m)
        case "icr":
            return PaperIcr()
        case "switching":
            return PaperSwitching(k1=cfg.k1, k2=cfg.k2, h_m=cfg.h_m)
        case "ours":
            return OursController(
                gain_per_s=cfg.gain_per_s,
                control_point_m=cfg.control_point_m,
                compensate_delay=cfg.compensate_delay,
            )
