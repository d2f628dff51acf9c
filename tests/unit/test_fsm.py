from dataclasses import dataclass

from phalanx.agents.behaviours.formation import FollowerBehaviour
from phalanx.agents.behaviours.leader import LeaderBehaviour, ScriptedProfile
from phalanx.agents.fsm import ANY_STATE, State, StateMachine, Transition
from phalanx.config import DeadlockConfig, LeaderProfile, Segment


@dataclass
class Ctx:
    x: int = 0


def test_priority_entry_exit_and_log() -> None:
    calls: list[str] = []
    fsm: StateMachine[Ctx] = StateMachine(
        initial="A",
        transitions=[
            Transition("A", "B", lambda c: c.x > 0, "x positive"),
            Transition("A", "C", lambda c: c.x > 5, "x large", priority=5),
            Transition(ANY_STATE, "A", lambda c: c.x < 0, "reset", priority=9),
        ],
        on_entry={"C": lambda c: calls.append("enter C")},
        on_exit={"A": lambda c: calls.append("exit A")},
    )
    assert fsm.update(Ctx(0), 0.0) is None
    event = fsm.update(Ctx(7), 1.0)
    assert event is not None
    assert (event.source, event.target, event.reason) == ("A", "C", "x large")
    assert calls == ["exit A", "enter C"]
    assert fsm.update(Ctx(-1), 2.0) is not None
    assert fsm.state == "A"
    assert fsm.update(Ctx(-1), 3.0) is None  # "*" never re-enters the state it is in
    assert [e.t_s for e in fsm.log] == [1.0, 2.0]
    assert fsm.states == ("A", "B", "C")


def test_follower_switches_on_leader_velocity_with_hysteresis() -> None:
    b = FollowerBehaviour(threshold_mps=0.02)
    b.observe(leader_v_mps=0.15, leader_direction=1, leader_fresh=True)
    b.update(0.0)
    assert b.fsm.state == State.FORMATION_TRACK
    assert b.direction == 1
    b.observe(leader_v_mps=-0.01, leader_direction=-1, leader_fresh=True)
    assert b.update(1.0) is None  # inside the band: no chatter
    b.observe(leader_v_mps=-0.05, leader_direction=-1, leader_fresh=True)
    assert b.update(2.0) is not None
    assert b.fsm.state == State.FORMATION_REVERSE
    assert b.direction == -1
    b.observe(leader_v_mps=0.05, leader_direction=1, leader_fresh=True)
    b.update(3.0)
    assert b.fsm.state == State.FORMATION_TRACK


def test_follower_holds_when_the_leader_goes_stale_and_resumes() -> None:
    b = FollowerBehaviour(threshold_mps=0.02)
    b.observe(leader_v_mps=-0.1, leader_direction=-1, leader_fresh=True)
    b.update(0.0)
    b.update(0.1)
    assert b.fsm.state == State.FORMATION_REVERSE
    b.observe(leader_v_mps=-0.1, leader_direction=-1, leader_fresh=False)
    event = b.update(0.2)
    assert event is not None
    assert event.target == State.HOLD
    assert "stale" in event.reason
    b.observe(leader_v_mps=-0.1, leader_direction=-1, leader_fresh=True)
    b.update(0.3)
    assert b.fsm.state == State.FORMATION_REVERSE


def test_profile_segments_and_end() -> None:
    profile = ScriptedProfile(
        LeaderProfile(
            segments=(
                Segment(duration_s=2.0, v_mps=0.1),
                Segment(duration_s=1.0, v_mps=0.2, omega_degps=90.0),
            )
        )
    )
    assert profile.twist_at(1.0).v_mps == 0.1
    assert profile.twist_at(2.5).omega_radps > 1.5
    assert profile.twist_at(3.5).v_mps == 0.0


def test_leader_reverses_a_safe_distance_when_everyone_is_blocked() -> None:
    b = LeaderBehaviour(
        LeaderProfile(segments=(Segment(duration_s=100.0, v_mps=0.15),)),
        DeadlockConfig(reverse_speed_mps=0.1, safe_distance_m=0.5),
    )
    b.observe(blocked=("r1",), everyone_blocked=False, odometry_step_m=0.0)
    assert b.update(0.0) is None
    b.observe(blocked=("r1", "r2"), everyone_blocked=True, odometry_step_m=0.0)
    assert b.update(0.1) is not None
    assert b.direction == -1
    assert b.wanted_twist(0.1).v_mps == -0.1
    t = 0.1
    while b.fsm.state == State.DEADLOCK_REVERSE and t < 20.0:
        t += 0.1
        b.observe(blocked=(), everyone_blocked=False, odometry_step_m=0.01)
        b.update(t)
    assert b.fsm.state == State.NAVIGATE
    assert t == __import__("pytest").approx(5.1, abs=0.15)  # 0.5 m at 0.01 m a step
