"""Which sense frames a simulated robot acts on (`phalanx.runtime.frames.FrameGate`)."""

from __future__ import annotations

from phalanx.runtime.frames import FINAL_CONFIRM_S, FrameGate
from phalanx.wire.codec import DecodeStats
from phalanx.wire.messages import SenseFrame

DT = 0.1


def frame(k: int, *, final: bool = False) -> SenseFrame:
    return SenseFrame(robot_id="r2", tick=k, t_s=k * DT, dt_s=DT, x_m=0.0, y_m=0.0,
                      theta_rad=0.0, v_mps=0.0, omega_radps=0.0, final=final)  # fmt: skip


class Clock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def gate(last_tick: int = 1999) -> tuple[FrameGate, DecodeStats, Clock]:
    stats, clock = DecodeStats(), Clock()
    return FrameGate(stats, last_tick=last_tick, dt_s=DT, clock=clock), stats, clock


def test_the_newest_frame_waiting_is_taken_and_the_rest_counted_skipped() -> None:
    g, stats, _ = gate()
    assert g.offer([frame(1)]).tick == 1  # type: ignore[union-attr]
    taken = g.offer([frame(2), frame(3), frame(4)])  # the robot was late: three waiting
    assert taken is not None
    assert taken.tick == 4
    assert g.counts.skipped == 2
    assert stats.dropped == 0  # late is not malformed


def test_a_frame_no_newer_than_the_last_is_refused_and_counted() -> None:
    g, stats, _ = gate()
    g.offer([frame(5)])
    assert g.offer([frame(5)]) is None
    assert g.offer([frame(3)]) is None
    assert stats.rejected["SenseFrame"] == 2


def test_a_jump_ahead_waits_for_the_next_tick_to_confirm_it() -> None:
    g, stats, _ = gate()
    g.offer([frame(5)])
    assert g.offer([frame(500)]) is None  # a lone frame far ahead: held
    assert g.offer([frame(6)]).tick == 6  # type: ignore[union-attr]  # the world goes on
    assert stats.rejected["SenseFrame"] == 1  # the jump was never confirmed: refused
    assert g.offer([frame(900)]) is None
    assert g.offer([frame(901)]).tick == 901  # type: ignore[union-attr]  # confirmed


def test_a_final_frame_at_the_runs_end_finishes_it() -> None:
    g, _, _ = gate(last_tick=10)
    g.offer([frame(10)])
    assert g.offer([frame(10, final=True)]) is None
    assert g.ended()
    assert g.ending == "finished"


def test_a_final_frame_mid_run_is_refuted_by_the_next_frame() -> None:
    g, stats, clock = gate()
    g.offer([frame(20)])
    assert g.offer([frame(20, final=True)]) is None
    clock.now_s = 1.0
    assert not g.ended()  # not yet: a world that still runs sends another frame
    assert g.offer([frame(21)]).tick == 21  # type: ignore[union-attr]
    clock.now_s = 10.0
    assert not g.ended()
    assert stats.rejected["SenseFrame"] == 1


def test_a_final_frame_mid_run_never_refuted_ends_the_run_cut_short() -> None:
    g, _, clock = gate()
    g.offer([frame(20)])
    g.offer([frame(20, final=True)])
    clock.now_s = FINAL_CONFIRM_S + 0.1
    assert g.ended()
    assert g.ending == "cut_short"  # an ending nobody asked for: not a finished run


def test_a_final_frame_at_the_end_far_ahead_finishes_the_run_once_confirmed() -> None:
    # The robot was frozen over the run's last ticks: the world's final frame comes far
    # ahead of the last it acted on. The run did end; but a lone frame far ahead could
    # be anyone's, so it ends the run only once no frame has followed it.
    g, _, clock = gate(last_tick=100)
    g.offer([frame(70)])
    g.offer([frame(100, final=True)])
    assert not g.ended()
    clock.now_s = FINAL_CONFIRM_S + 0.1
    assert g.ended()
    assert g.ending == "finished"
