"""Wire encodings compared: JSON (pydantic) against the packed binary form.

Prints, for each message kind, the payload size and the encode and decode time per
message (best of several rounds, so a busy machine's noise shows less), and the ratio
JSON / packed in the same run.

    .venv/bin/python bench/bench_codec.py [--rounds 5] [--n 20000]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

from calibration import Calibration

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


if __name__ == "__main__":
    main()
