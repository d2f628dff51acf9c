"""Driver backends against their emulated robots: latency, parsing rate, time to stop.

For ARCOS (emulator over a pty and over TCP) and CiA 402 (two simulated drives on
python-can's virtual bus), prints:
- command -> robot: set_velocity() until the robot side has the new setpoint (emulator
  firmware setpoint, drive target velocity);
- command -> motion seen: from rest, set_velocity() until the driver's odometry shows the
  robot moving (ARCOS: the next SIP, every 100 ms; CAN: the next TPDO, every 20 ms);
- frames parsed per second: the ARCOS frame parser and SIP decoder on a recorded stream;
- lost link -> motors stopped: ARCOS cable unplugged (silence both ways) until the
  firmware watchdog stops the motors (2 s on a P3DX) and until the driver reports the link
  lost; CAN heartbeat lost until both wheels are commanded to zero;
- ARCOS SIPs lost while the link still carries commands (docs/RELIABILITY.md): the driver
  declaring them lost -> its STOP arriving at the robot, and -> the robot at rest; the
  longest control-step call (set_velocity, read_odometry, read_status at 20 Hz) while the
  driver reconnects to a silent robot, against one control period (50 ms).

    .venv/bin/python bench/bench_drivers.py [--repeats 30] [--only sip-loss]
"""

from __future__ import annotations

import argparse
import contextlib
import math
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from calibration import Calibration

from phalanx.core.config_files import load_robot
from phalanx.core.errors import DriverError
from phalanx.core.geometry import Twist2D
from phalanx.drivers.arcos import ArcosDriver, ArcosSettings
from phalanx.drivers.canopen import CanopenDriver, CanopenSettings
from phalanx.protocols.arcos import FrameParser, Sip, decode_sip, encode_sip
from phalanx.simulator.arcos_emulator import ArcosEmulator, Link, PtyLink, TcpLink
from phalanx.simulator.cia402 import SimulatedDiffDrive

ROBOT = load_robot("p3dx")


def _until(check: Callable[[], bool], timeout_s: float = 5.0) -> float:
    started = time.perf_counter()
    while not check():
        if time.perf_counter() - started > timeout_s:
            return float("nan")
        time.sleep(0.0002)
    return time.perf_counter() - started


def _pct(values: list[float]) -> str:
    values = sorted(v for v in values if v == v)
    if not values:
        return "n/a"
    p99 = values[min(len(values) - 1, round(0.99 * (len(values) - 1)))]
    return f"p50 {1e3 * statistics.median(values):7.2f} ms  p99 {1e3 * p99:7.2f} ms"


@contextmanager
def arcos(link: Link) -> Iterator[tuple[ArcosEmulator, ArcosDriver]]:
    with ArcosEmulator(link, ROBOT) as emulator:
        where = link.device if isinstance(link, PtyLink) else None
        settings = (
            ArcosSettings(port=where) if where else ArcosSettings(tcp=f"127.0.0.1:{link.port}")  # type: ignore[attr-defined]
        )
        with ArcosDriver(settings, robot=ROBOT) as driver:
            yield emulator, driver


def arcos_latency(name: str, link: Link, repeats: int) -> None:
    to_robot, to_motion = [], []
    with arcos(link) as (emulator, driver):
        for i in range(repeats):
            v = 0.1 if i % 2 == 0 else -0.1
            driver.set_velocity(Twist2D(0.0, 0.0))  # from rest: latency, not acceleration
            _until(lambda: driver.read_odometry().twist.v_mps == 0.0)
            t0 = time.perf_counter()
            driver.set_velocity(Twist2D(v, 0.0))
            to_robot.append(_until(lambda v=v: emulator.target.v_mps == v))
            t1 = time.perf_counter() - t0
            seen = _until(lambda v=v: driver.read_odometry().twist.v_mps * v > 0.0)
            to_motion.append(t1 + seen)
        driver.stop()
    print(f"arcos {name:4s} command -> robot setpoint   {_pct(to_robot)}")
    print(f"arcos {name:4s} command -> motion in SIP    {_pct(to_motion)}")


def arcos_unplug(repeats: int) -> None:
    stopped, noticed = [], []
    for _ in range(repeats):
        # A serial cable (a pty): no connection to drop, only the firmware watchdog is left.
        with arcos(PtyLink()) as (emulator, driver):
            driver.set_velocity(Twist2D(0.2, 0.0))
            _until(lambda: emulator.body.state().twist.v_mps > 0.1)
            t0 = time.perf_counter()
            emulator.unplug()
            noticed.append(_until(lambda: not driver.link_up))
            stopped.append(
                time.perf_counter() - t0 + _until(lambda: emulator.body.state().twist.v_mps == 0.0)
            )
            emulator.unplug(False)
    print(f"arcos unplugged -> driver reports link lost {_pct(noticed)}")
    print(f"arcos unplugged -> motors stopped (firmware watchdog 2 s) {_pct(stopped)}")


def arcos_sip_loss(repeats: int) -> None:
    to_stop, to_rest = [], []
    for _ in range(repeats):
        with arcos(TcpLink(0)) as (emulator, driver):
            driver.set_velocity(Twist2D(0.2, 0.0))
            _until(lambda: emulator.body.state().twist.v_mps > 0.19)
            emulator.drop_sips(20)  # SIPs stop; commands still reach the robot
            _until(lambda: driver.stats.sips_lost_s is not None, timeout_s=5.0)
            lost_s = driver.stats.sips_lost_s or float("nan")
            _until(lambda s=lost_s: emulator.stats.first_after("STOP", s) is not None)
            to_stop.append((emulator.stats.first_after("STOP", lost_s) or math.nan) - lost_s)
            _until(lambda: emulator.body.state().twist.v_mps == 0.0)
            to_rest.append(time.monotonic() - lost_s)
    worst = max(to_stop) * 1e3
    print(f"arcos SIPs lost -> STOP at the robot        {_pct(to_stop)} (max {worst:.2f} ms)")
    print(f"arcos SIPs lost -> robot at rest (0.2 m/s)  {_pct(to_rest)}")


def arcos_reconnect_blocking(seconds: float) -> None:
    calls: list[float] = []
    with arcos(TcpLink(0)) as (emulator, driver):
        emulator.unplug()  # silence: every reconnect attempt runs into its timeouts
        started = time.monotonic()
        while time.monotonic() - started < seconds:
            for call in (driver.read_odometry, driver.read_status,
                         lambda: driver.set_velocity(Twist2D(0.2, 0.0))):  # fmt: skip
                t0 = time.perf_counter()
                with contextlib.suppress(DriverError):
                    call()
                calls.append(time.perf_counter() - t0)
            time.sleep(0.05)
        attempts = driver.stats.reconnect_failures
    print(
        f"arcos control calls while reconnecting ({attempts} attempts in {seconds:.0f} s): "
        f"{_pct(calls)}, longest {max(calls) * 1e3:.2f} ms (one control period: 50 ms)"
    )


def parse_rate() -> None:
    sip = Sip(moving=True, x=1000, y=2000, th=100, left_vel=150, right_vel=160,
              battery_dv=125, stall_bumpers=0, flags=1,
              sonars=tuple((i, 1000 + i) for i in range(16)), rot_vel_x10=12)  # fmt: skip
    stream = encode_sip(sip) * 20000
    started = time.perf_counter()
    frames = 0
    parser = FrameParser()
    for offset in range(0, len(stream), 4096):
        for body in parser.feed(stream[offset : offset + 4096]):
            decode_sip(body)
            frames += 1
    rate = frames / (time.perf_counter() - started)
    print(
        f"arcos frame parser + SIP decode: {rate:,.0f} SIPs/s ({len(encode_sip(sip))} B each; "
        f"a P3DX sends 10/s)"
    )


def _can_rig(channel: str) -> tuple[list[float], list[float], float, float]:
    """One simulated robot: (command -> target, command -> TPDO motion, TPDO rate, stop)."""
    to_drive, to_motion = [], []
    with SimulatedDiffDrive(channel) as drives:
        driver = CanopenDriver(CanopenSettings(interface="virtual", channel=channel), robot=ROBOT)
        driver.connect()
        for j in range(10):
            v = 0.1 if j % 2 == 0 else -0.1
            driver.set_velocity(Twist2D(0.0, 0.0))  # from rest: latency, not acceleration
            _until(lambda: abs(driver.read_odometry().twist.v_mps) < 1e-4)
            t0 = time.perf_counter()
            driver.set_velocity(Twist2D(v, 0.0))
            to_drive.append(_until(lambda v=v: drives.left.target * v > 0))
            t1 = time.perf_counter() - t0
            moving = _until(lambda v=v: driver.read_odometry().twist.v_mps * v > 1e-3)
            to_motion.append(t1 + moving)
        n0, t0 = driver.stats.tpdos, time.perf_counter()
        time.sleep(1.0)
        rate = (driver.stats.tpdos - n0) / (time.perf_counter() - t0)
        drives.right.lose_heartbeat()
        stop = _until(lambda: drives.left.target == 0 and bool(driver.stats.faults))
        driver.close()
    return to_drive, to_motion, rate, stop


def can_latency(repeats: int) -> None:
    to_drive, to_motion, rates, stops = [], [], [], []
    for i in range(max(3, repeats // 10)):
        a, b, rate, stop = _can_rig(f"bench{i}")
        to_drive += a
        to_motion += b
        rates.append(rate)
        stops.append(stop)
    print(f"canopen command -> drive target (RPDO)   {_pct(to_drive)}")
    print(f"canopen command -> motion in TPDO         {_pct(to_motion)}")
    print(f"canopen TPDOs processed: {statistics.mean(rates):.0f}/s (2 drives x 50 Hz)")
    print(f"canopen heartbeat lost -> wheels zero    {_pct(stops)} (timeout 300 ms, beats 50 ms)")


def main() -> None:
    Calibration.measure()  # (the unit every time below can be divided by, on any machine)
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--only", choices=["sip-loss", "unplug"], default=None)
    args = parser.parse_args()
    if args.only == "unplug":
        arcos_unplug(max(3, args.repeats // 10))
        return
    if args.only == "sip-loss":
        arcos_sip_loss(args.repeats)
        arcos_reconnect_blocking(20.0)
        return
    arcos_latency("pty", PtyLink(), args.repeats)
    arcos_latency("tcp", TcpLink(0), args.repeats)
    parse_rate()
    arcos_unplug(max(3, args.repeats // 10))
    arcos_sip_loss(max(3, args.repeats // 3))
    arcos_reconnect_blocking(10.0)
    can_latency(args.repeats)


if __name__ == "__main__":
    main()
