"""Wire encodings compared: JSON (pydantic) against the packed binary form.

Prints, for each message kind, the payload size and the encode and decode time per
message (best of several rounds, so a busy machine's noise shows less), and the ratio
JSON / packed in the same run. Then a lockstep world's tick: N frames, each carrying the
other N - 1 robots' states, packed with each state packed once a tick (as the codec does)
and with each state packed again in every frame (as it did), in the same run.

    .venv/bin/python bench/bench_codec.py [--rounds 5] [--n 20000] [--robots 3 10 30]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

from calibration import Calibration

from phalanx.wire import codec
from phalanx.wire.codec import decode, encode
from phalanx.wire.messages import Message, RobotState, SenseFrame, VelocityCommand


def samples() -> list[Message]:
    """One realistic message of each kind that travels every control period."""
    return [
        RobotState(
            robot_id="r2",
            seq=1234,
            stamp_s=101.3,
            x_m=3.21,
            y_m=-0.71,
            theta_rad=0.12,
            v_mps=-0.149,
            omega_radps=0.052,
            fsm_state="FORMATION_REVERSE",
            obstacle=True,
            direction=-1,
            leader_id="r1",
            epoch=2,
        ),
        VelocityCommand(robot_id="r2", tick=1013, stamp_s=101.3, v_mps=-0.149, omega_radps=0.052),
        SenseFrame(
            robot_id="r2",
            tick=1013,
            t_s=101.3,
            dt_s=0.1,
            x_m=3.21,
            y_m=-0.71,
            theta_rad=0.12,
            v_mps=-0.149,
            omega_radps=0.052,
            sonar_ranges_m=tuple(0.3 + 0.1 * i for i in range(16)),
            bumpers=(False,) * 10,
        ),
    ]


def lockstep_tick(n: int) -> list[SenseFrame]:
    """A lockstep tick's frames for `n` robots, each with every other robot's state."""
    state = samples()[0]
    assert isinstance(state, RobotState)  # noqa: S101
    frame = samples()[2]
    states = [state.model_copy(update={"robot_id": f"r{i}"}) for i in range(n)]
    return [
        frame.model_copy(
            update={"robot_id": s.robot_id, "peers": tuple(p for p in states if p is not s)}
        )
        for s in states
    ]


def tick_figures(robots: list[int], rounds: int, cal: Calibration) -> None:
    """Packing a lockstep tick's frames, each state once against once per frame."""
    print("\nlockstep tick  robots  bytes/frame  once_us  per_frame_us  ratio  once_ucal")
    for n in robots:
        frames = lockstep_tick(n)

        def once(frames: list[SenseFrame] = frames) -> None:
            codec._NESTED.clear()  # a new tick: its states are new messages
            for f in frames:
                encode(f, "packed")

        def per_frame(frames: list[SenseFrame] = frames) -> None:
            for f in frames:
                codec._NESTED.clear()  # (how the codec packed before: every frame anew)
                encode(f, "packed")

        reps = max(1, 3000 // (n * n))
        a, b = best_us(once, reps, rounds), best_us(per_frame, reps, rounds)
        size = len(encode(frames[0], "packed"))
        ucal = cal.ratio(a)
        print(f"{'':14s} {n:6d}  {size:11d}  {a:7.0f}  {b:12.0f}  {b / a:5.2f}  {ucal:9.1f}")


def best_us(action: Callable[[], object], n: int, rounds: int) -> float:
    """Best mean time of `action` over `rounds` rounds of `n` calls, in microseconds."""
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(n):
            action()
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e6


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--n", type=int, default=20000)
    parser.add_argument("--robots", type=int, nargs="*", default=[3, 10, 30])
    args = parser.parse_args()
    cal = Calibration.measure()
    print("message          format  bytes  encode_us  decode_us  encode_ucal  decode_ucal")
    for message in samples():
        kind = type(message)
        figures = {}
        for fmt in ("json", "packed"):
            payload = encode(message, fmt)
            assert decode(kind, payload) == message  # noqa: S101 - the round trip holds
            enc = best_us(lambda m=message, f=fmt: encode(m, f), args.n, args.rounds)
            dec = best_us(lambda p=payload, k=kind: decode(k, p), args.n, args.rounds)
            figures[fmt] = (len(payload), enc, dec)
            print(
                f"{kind.__name__:16s} {fmt:6s}  {len(payload):5d}  {enc:9.2f}  {dec:9.2f}  "
                f"{cal.ratio(enc):11.1f}  {cal.ratio(dec):11.1f}"
            )
        (jb, je, jd), (pb, pe, pd) = figures["json"], figures["packed"]
        print(f"{'':16s} ratio   {jb / pb:5.2f}  {je / pe:9.2f}  {jd / pd:9.2f}  (json / packed)")
    tick_figures(args.robots, args.rounds, cal)


if __name__ == "__main__":
    main()
