"""`CycleClock`: a robot sends a packet every cycle; the host reads them late by whatever
its scheduler makes it (a loaded machine: tens of milliseconds, then a burst). Stamped
on the cycle, a packet's time is never after its arrival, never goes back, and is off
the time it was sent (plus the link's own latency) by at most the clock's slack a cycle
since the last packet that came on time, where its arrival is off by all the delay."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from phalanx.drivers.arcos_tracker import CYCLE_SLACK, CycleClock

LATENCY_S = 0.004  # the link's own, the least a packet takes


@given(
    period_s=st.floats(0.02, 0.2),
    stretch=st.floats(1.0, 1.0 + CYCLE_SLACK),
    delays_s=st.lists(st.floats(0.0, 0.5), min_size=1, max_size=60),
)
def test_stamps_keep_to_the_cycle_however_late_the_reader(
    period_s: float, stretch: float, delays_s: list[float]
) -> None:
    clock = CycleClock()
    delays_s = [0.0, *delays_s]  # the first packet on time
    sent = [k * period_s * stretch for k in range(len(delays_s))]
    # The reader takes packets in order: one held up holds up those behind it.
    arrived, latest = [], 0.0
    for sent_s, delay_s in zip(sent, delays_s, strict=True):
        latest = max(latest, sent_s + LATENCY_S + delay_s)
        arrived.append(latest)
    stamps = [clock.stamp(a, period_s) for a in arrived]
    on_time = 0
    for k, (stamp, arrival) in enumerate(zip(stamps, arrived, strict=True)):
        truth = sent[k] + LATENCY_S
        if arrival - truth < 1e-12:
            on_time = k
        assert stamp <= arrival
        assert k == 0 or stamp >= stamps[k - 1]
        assert -1e-9 <= stamp - truth <= (k - on_time) * period_s * CYCLE_SLACK + 1e-9


def test_a_lost_frame_restarts_the_cycle_at_the_next_arrival() -> None:
    clock = CycleClock()
    assert clock.stamp(10.0, 0.1) == 10.0
    assert clock.stamp(10.35, 0.1) == 10.0 + 0.1 * (1.0 + CYCLE_SLACK)  # late: on the cycle
    clock.lose()  # a frame between may be gone: the next is not a cycle on
    assert clock.stamp(10.5, 0.1) == 10.5
    assert clock.stamp(10.9, 0.0) == 10.9  # no cycle known: the arrival
