"""Leadership over shared flags: the re-rooted tracking tree, handover, loss, the epoch
rule, and the deadlock rule; every robot deciding alike from the same flags."""

from __future__ import annotations

from collections import Counter
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from peerflags import flags

from phalanx.agents.leadership import Leadership, LiveFlags, group_deadlock, newer
from phalanx.agents.memory import StopsBefore
from phalanx.core.config import LeadershipConfig
from phalanx.core.formation import Formation, resolve_formation
from phalanx.core.scenarios import formation_shape
from phalanx.core.states import OUT_OF_FORMATION, State
from phalanx.wire.keys import leader_key
from phalanx.wire.messages import RobotFlags

WEDGE = resolve_formation(formation_shape("wedge", 3))
INLINE = resolve_formation(formation_shape("inline", 3))
WEDGE4 = resolve_formation(formation_shape("wedge", 4))
CONFIG = LeadershipConfig()
TIMEOUT_S = 0.5


def views(formation: Formation, **kw: Any) -> dict[str, Leadership]:
    out = {}
    for rid in formation.robot_ids:
        view = Leadership(rid, formation, LeadershipConfig(**kw), timeout_s=TIMEOUT_S)
        view.since_s = -100.0  # long in office: tenure never the reason in these tests
        out[rid] = view
    return out


def blocked_leader(t_s: float = 10.0) -> dict[str, RobotFlags]:
    return {
        "r1": flags("r1", t_s, obstacle=True, blocked_s=0.5, clear=False),
        "r2": flags("r2", t_s),
        "r3": flags("r3", t_s),
    }


def test_tree_is_rerooted_at_any_leader() -> None:
    assert INLINE.reroot("r3") == {"r1": "r2", "r2": "r3", "r3": None}
    assert WEDGE.reroot("r2") == {"r1": "r2", "r2": None, "r3": "r1"}
    assert WEDGE.tree_path("r3", "r2") == ("r1", "r2")


def test_tracking_skips_gone_and_out_of_formation_robots() -> None:
    view = views(INLINE)["r3"]
    everyone = {r: flags(r) for r in INLINE.robot_ids}
    assert view.tracked(everyone) == "r2"
    avoiding = everyone | {"r2": flags("r2", fsm_state=State.AVOID, formed=False)}
    assert view.tracked(avoiding) == "r1"  # r2 left its slot: track its leader instead
    gone = {r: f for r, f in everyone.items() if r != "r2"}
    assert view.tracked(gone) == "r1"
    assert views(INLINE)["r1"].tracked(everyone) is None


def test_every_robot_hands_over_to_the_same_clear_follower() -> None:
    decisions = set()
    for rid, view in views(WEDGE).items():
        change = view.update(view.live(blocked_leader(), 10.05), 10.05)
        assert change is not None, rid
        decisions.add((view.leader_id, view.epoch))
    # r2 and r3 are equally clear and forward: the formation's order decides.
    assert decisions == {("r2", 1)}


def test_the_new_tree_tracks_neighbours() -> None:
    view = views(WEDGE)["r3"]
    view.update(view.live(blocked_leader(), 10.05), 10.05)
    after = blocked_leader() | {"r1": flags("r1", fsm_state=State.FORMATION_TRACK)}
    assert view.tracked(after) == "r1"  # r3 keeps its neighbour r1, now following r2


@pytest.mark.parametrize(
    ("why", "overrides", "kw"),
    [
        ("not blocked long enough", {"r1": {"blocked_s": 0.1}}, {}),
        ("every robot blocked", {"r2": {"obstacle": True}, "r3": {"obstacle": True}}, {}),
        ("nobody clear", {"r2": {"clear": False}, "r3": {"clear": False}}, {}),
        ("a dead end, not a local obstacle", {"r1": {"dead_end": True}}, {}),
        ("the leader is reversing", {"r1": {"fsm_state": State.DEADLOCK_REVERSE}}, {}),
        ("handover switched off", {}, {"handover": False}),
    ],
)
def test_no_handover(why: str, overrides: dict[str, dict[str, Any]], kw: dict[str, Any]) -> None:
    shared = blocked_leader()
    for rid, changes in overrides.items():
        shared[rid] = shared[rid].model_copy(update=changes)
    view = views(WEDGE, **kw)["r2"]
    assert view.update(view.live(shared, 10.05), 10.05) is None, why
    assert (view.leader_id, view.epoch) == ("r1", 0)


def test_no_handover_within_the_tenure() -> None:
    view = Leadership("r2", WEDGE, CONFIG, timeout_s=TIMEOUT_S)
    view.since_s = 9.0  # leader since 1 s ago, min_tenure_s = 3
    assert view.update(view.live(blocked_leader(), 10.05), 10.05) is None


def test_a_late_message_cannot_flip_leadership_back() -> None:
    view = views(WEDGE)["r3"]
    moved = {r: flags(r, formation_leader_id="r2", epoch=2) for r in ("r1", "r2")}
    view.update(moved, 10.0)  # (held by two of three: a robot that missed a change catches up)
    assert (view.leader_id, view.epoch) == ("r2", 2)
    late = {"r1": flags("r1", formation_leader_id="r1", epoch=1, fsm_state=State.NAVIGATE)}
    assert view.update(late | {"r2": flags("r2", formation_leader_id="r2", epoch=2)}, 10.1) is None
    assert (view.leader_id, view.epoch) == ("r2", 2)


def test_a_lead_the_fleet_did_not_follow_is_handed_back() -> None:
    """The race on ARCOS's sonar ring: r2 takes the lead from a blocked r1 on its own
    flags still clear; by the time r1 and r3 hear the claim r2's flags are blocked too,
    every robot is (r1's deadlock, not a handover), and they refuse it. r2, alone in its
    pair, goes back to theirs once the change has had time to spread; not before.
    """
    fleet = views(WEDGE)
    r1, r2 = fleet["r1"], fleet["r2"]
    assert r2.update(r2.live(blocked_leader(20.2), 20.2), 20.2) is not None
    assert (r2.leader_id, r2.epoch) == ("r2", 1)
    blocked = {"obstacle": True, "blocked_s": 0.1, "clear": False}
    claim = {"formation_leader_id": "r2", "epoch": 1, "fsm_state": State.NAVIGATE}

    def heard(t_s: float) -> dict[str, RobotFlags]:
        return {
            "r1": flags("r1", t_s, obstacle=True, blocked_s=0.5, clear=False),
            "r2": flags("r2", t_s, **blocked, **claim),
            "r3": flags("r3", t_s, **blocked),
        }

    assert r1.update(r1.live(heard(20.3), 20.3), 20.3) is None
    assert (r1.leader_id, r1.epoch) == ("r1", 0)
    assert r1.refused == 1
    assert r2.update(r2.live(heard(21.0), 21.0), 21.0) is None  # the change still spreading
    assert (r2.leader_id, r2.epoch) == ("r2", 1)
    change = r2.update(r2.live(heard(21.8), 21.8), 21.8)
    assert change is not None
    assert "not followed" in change.reason
    assert (r2.leader_id, r2.epoch) == ("r1", 0)


def test_a_lead_another_robot_followed_is_kept() -> None:
    """r2's lead, held by r3 as well, stays: no step back; r1, alone, catches up."""
    fleet = views(WEDGE)
    r1, r2 = fleet["r1"], fleet["r2"]
    r2.update(r2.live(blocked_leader(20.2), 20.2), 20.2)
    claim = {"formation_leader_id": "r2", "epoch": 1}
    heard = {
        "r1": flags("r1", 25.0, obstacle=True, blocked_s=0.5, clear=False),
        "r2": flags("r2", 25.0, fsm_state=State.NAVIGATE, **claim),
        "r3": flags("r3", 25.0, **claim),
    }
    assert r2.update(r2.live(heard, 25.0), 25.0) is None
    assert (r2.leader_id, r2.epoch) == ("r2", 1)
    assert r1.update(r1.live(heard, 25.0), 25.0) is not None
    assert (r1.leader_id, r1.epoch) == ("r2", 1)


def test_a_lead_taken_from_a_leader_out_of_hearing_is_kept() -> None:
    """Cut off from r1 (r3 still hears it), r2 leads under epoch 1 by rule 3; r1's pair,
    which r3 holds, is no pair to go back to while r2 does not hear r1.
    """
    r2 = views(WEDGE)["r2"]
    r2.leader_id, r2.epoch, r2.since_s = "r2", 1, 20.0
    heard = {"r2": flags("r2", 25.0, formation_leader_id="r2", epoch=1), "r3": flags("r3", 25.0)}
    assert r2.update(r2.live(heard, 25.0), 25.0) is None
    assert (r2.leader_id, r2.epoch) == ("r2", 1)


def test_the_robot_a_leader_hands_to_takes_the_lead_its_own_view_would_not_pick() -> None:
    """r1 handed the lead to r3 on flags that showed r2 blocked; r2 is clear now, and r3's
    view would pick r2 (the formation's order). r3 takes it: refusing, it would follow r1
    while r1 follows r3, and no robot would lead.
    """
    r3 = views(WEDGE4)["r3"]
    handed = {"formation_leader_id": "r3", "epoch": 1}
    heard = {
        "r1": flags("r1", 3.1, fsm_state=State.FORMATION_TRACK, **handed),
        "r2": flags("r2", 3.1, **handed),
        "r3": flags("r3", 3.1),
        "r4": flags("r4", 3.1),
    }
    assert r3.update(r3.live(heard, 3.1), 3.1) is not None
    assert (r3.leader_id, r3.epoch) == ("r3", 1)


def test_a_robot_whose_leader_follows_another_claim_at_its_epoch_follows_it_too() -> None:
    """Two robots took the lead at epoch 1 on different flags; r1 and r4 followed r3, and
    r3 has since followed r2's claim (two robots a pair, no majority): r1 follows on to r2.
    """
    r1 = views(WEDGE4)["r1"]
    r1.leader_id, r1.epoch, r1.since_s = "r3", 1, 3.0
    heard = {
        "r1": flags("r1", 3.2, fsm_state=State.FORMATION_TRACK, formation_leader_id="r3", epoch=1),
        "r2": flags("r2", 3.2, fsm_state=State.NAVIGATE, formation_leader_id="r2", epoch=1),
        "r3": flags("r3", 3.2, formation_leader_id="r2", epoch=1),
        "r4": flags("r4", 3.2, formation_leader_id="r3", epoch=1),
    }
    assert r1.update(r1.live(heard, 3.2), 3.2) is not None
    assert (r1.leader_id, r1.epoch) == ("r2", 1)


def test_same_epoch_two_claims_converge_on_the_formation_order() -> None:
    assert newer((3, "r2"), (3, "r3"), WEDGE)
    assert not newer((3, "r3"), (3, "r2"), WEDGE)
    assert newer((4, "r3"), (3, "r2"), WEDGE)
    assert not newer((4, "nobody"), (3, "r2"), WEDGE)


def test_a_lost_leader_is_replaced_after_the_grace_by_the_best_live_robot() -> None:
    shared = {"r2": flags("r2", clear=False), "r3": flags("r3", clear=True)}
    view = views(WEDGE)["r2"]
    view.leader_heard_s = 10.0
    assert view.leader_lost(view.live(shared, 10.1))
    assert view.update(view.live(shared, 10.1), 10.1) is None  # within timeout + grace
    change = view.update(
        view.live({r: flags(r, 11.6, clear=(r == "r3")) for r in shared}, 11.6), 11.6
    )
    assert change is not None
    assert (change.leader_id, change.epoch, change.previous_id) == ("r3", 1, "r1")
    assert "silent" in change.reason


def test_a_robot_never_declares_itself_lost() -> None:
    view = views(WEDGE)["r1"]
    assert not view.leader_lost({})
    assert view.update({}, 100.0) is None


def test_stale_flags_do_not_count() -> None:
    view = views(WEDGE)["r2"]
    assert set(view.live(blocked_leader(10.0), 10.0 + TIMEOUT_S + 0.01)) == set()


def test_deadlock_rule() -> None:
    everyone = {r: flags(r, obstacle=True, blocked_s=0.1, clear=False) for r in WEDGE.robot_ids}
    assert "every robot blocked" in group_deadlock(everyone, "r1", confirm_s=0.2)
    lonely = blocked_leader() | {r: flags(r, clear=False) for r in ("r2", "r3")}
    assert "no robot clear" in group_deadlock(lonely, "r1", confirm_s=0.2)
    assert group_deadlock(lonely, "r1", confirm_s=0.2, widened=False) == ""  # the paper's
    assert group_deadlock(blocked_leader(), "r1", confirm_s=0.2) == ""  # someone can lead
    dead_end = blocked_leader() | {"r1": flags("r1", obstacle=True, blocked_s=0.5, dead_end=True)}
    assert "dead end" in group_deadlock(dead_end, "r1", confirm_s=0.2)


def test_the_papers_rule_counts_a_column_queued_behind_a_blocked_robot() -> None:
    """A wall across a column's path: only the leader's sonar sees it; the robots queued
    behind it are blocked by it (their path is its), so the paper's rule holds."""
    leader = {"r1": flags("r1", obstacle=True, blocked_s=0.1, clear=False)}
    column = leader | {r: flags(r, clear=False) for r in ("r2", "r3")}
    queued = {"r2": "r1", "r3": "r2"}
    assert "every robot blocked" in group_deadlock(
        column, "r1", confirm_s=0.2, widened=False, queued=queued
    )
    assert group_deadlock(column, "r1", confirm_s=0.2, widened=False) == ""  # no column
    beside = {"r2": "r1"}  # r3 is not behind anyone: it must see the wall itself
    assert group_deadlock(column, "r1", confirm_s=0.2, widened=False, queued=beside) == ""
    loop = {"r2": "r3", "r3": "r2"}  # (a bad map never hangs it)
    assert group_deadlock(column, "r1", confirm_s=0.2, widened=False, queued=loop) == ""


def test_leader_key() -> None:
    assert leader_key("lab") == "phalanx/lab/leader"


robot_flags = st.builds(
    lambda state, direction, epoch, leader: {
        "fsm_state": state, "direction": direction, "epoch": epoch, "formation_leader_id": leader,
    },
    st.sampled_from([State.NAVIGATE, State.FORMATION_TRACK, State.EMERGENCY_STOP, State.HOLD,
                     State.AVOID, State.JOIN, State.DEADLOCK_REVERSE]),
    st.sampled_from([1, -1]),
    st.integers(0, 2),
    st.sampled_from(["r1", "r2", "r3", ""]),
)  # fmt: skip


@settings(max_examples=200, deadline=None)
@given(
    heard=st.dictionaries(st.sampled_from(WEDGE.robot_ids), robot_flags),
    before=st.frozensets(st.sampled_from(WEDGE.robot_ids)),
    cut_by=st.frozensets(st.sampled_from(WEDGE.robot_ids)),
    reversing=st.booleans(),
)
def test_the_flags_summaries_and_the_stops_remembered_are_their_rules(
    heard: dict[str, dict[str, Any]],
    before: frozenset[str],
    cut_by: frozenset[str],
    reversing: bool,
) -> None:
    """What every step reads of the flags (worked out once, in one pass), and the stops
    a leader passes over (kept every step: none while nobody is stopped).
    """
    live = LiveFlags({r: flags(r, **kw) for r, kw in heard.items()}, WEDGE)
    values = list(live.values())
    assert live.claims == Counter(
        (f.epoch, f.formation_leader_id) for f in values if f.formation_leader_id in WEDGE.rank
    )
    stopped = {r for r, f in live.items() if f.fsm_state == State.EMERGENCY_STOP}
    assert live.stopped == stopped
    assert live.stopped_behind == {r for r in stopped if live[r].direction < 0}
    out = OUT_OF_FORMATION | {State.HOLD}
    assert live.busy == {r for r, f in live.items() if f.fsm_state in out}
    stops = StopsBefore(before, cut_by)
    stops.update(live, "r2", reversing=reversing)
    cut = cut_by & live.stopped_behind
    kept = before & stopped if reversing else stopped - (live.stopped_behind - cut) - {"r2"}
    assert (stops.before, stops.cut_by) == (kept, cut)
    assert stops.someone_stopped(live, "r2") == bool(stopped - {"r2"} - kept)
