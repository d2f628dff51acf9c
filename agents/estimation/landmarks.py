"""Whose relative measurements a robot may fuse: the robots before it on the follow tree
rooted at the formation's leader (nearer the leader, or as near and earlier in the
formation's order). The order makes the frames flow one way, from the leader out: a
robot never corrects itself from a robot that corrects itself from it. In the paper's
inline formation the last robot's leader is hidden behind the middle robot, which it
sees instead: the middle robot's estimate lives in the leader's frame, so the last
robot's does too.
"""

from __future__ import annotations

from collections.abc import Mapping

from phalanx.core.formation import Formation
from phalanx.core.peers import PeerState


class Landmarks:
    """One robot's view of which other robots' states anchor its relative measurements."""

    def __init__(self, formation: Formation, robot_id: str) -> None:
        self.formation, self.robot_id = formation, robot_id
        self._cache: dict[str, frozenset[str]] = {}

    def upstream(self, leader_id: str) -> frozenset[str]:
        """The robots before this one when `leader_id` leads."""
        if leader_id not in self._cache:
            order = self.formation.robot_ids

            def key(rid: str) -> tuple[int, int]:
                depth = 0 if rid == leader_id else len(self.formation.tree_path(rid, leader_id))
                return depth, order.index(rid)

            own = key(self.robot_id)
            self._cache[leader_id] = frozenset(r for r in order if key(r) < own)
        return self._cache[leader_id]

    def pick(
        self, peers: Mapping[str, PeerState], leader_id: str, *, t_s: float, max_age_s: float
    ) -> dict[str, PeerState]:
        """The fresh states of the robots before this one."""
        before = self.upstream(leader_id)
        return {
            rid: state
            for rid, state in peers.items()
            if rid in before and t_s - state.stamp_s <= max_age_s
        }
