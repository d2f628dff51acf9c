"""Several hosts on one Linux machine: network namespaces joined by a bridge.

`NetLab` makes one network namespace per host (loopback up, IPv6 off: only IPv4 works,
as on the hosts phalanx must support), a switch namespace holding a bridge, and a veth
link from each host to the switch. A host's link can be taken down and up again (the
cable pulled and plugged back: the far end sees silence, not a reset). Needs root and
iproute2; `unavailable()` says why a machine cannot. Used by tests/multihost and
bench/bench_multihost.py.

`python lab/netlab.py observe --fleet F --connect EP` prints, one JSON object per
line, what a fleet's world and robots publish (sense frames, states, liveliness), each
stamped with CLOCK_MONOTONIC, which every namespace of a machine shares.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any, Self

from phalanx.core.lifecycle import Closing

PREFIX = "phxlab"
_counter = itertools.count()
_STALE = re.compile(rf"^{PREFIX}(\d+)x\d+-")


def _ip_path() -> str:
    return shutil.which("ip") or "/usr/sbin/ip"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [_ip_path(), *args], capture_output=True, text=True, timeout=10, check=check
    )


def unavailable() -> str | None:
    """Why network namespaces cannot be made here, or None if they can."""
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "making network namespaces needs root"
    if shutil.which("ip") is None:
        return "iproute2's `ip` is not installed"
    probe = f"{PREFIX}{os.getpid()}x{next(_counter)}-probe"
    made = _ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"`ip netns add` failed: {made.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


def reap_stale() -> None:
    """Delete namespaces left by labs whose process is gone (a killed test run)."""
    listing = _ip("netns", "list", check=False).stdout
    for line in listing.splitlines():
        name = line.split()[0] if line.strip() else ""
        match = _STALE.match(name)
        if match and not _pid_alive(int(match.group(1))):
            _kill_inside(name)
            _ip("netns", "del", name, check=False)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _kill_inside(namespace: str) -> None:
    pids = _ip("netns", "pids", namespace, check=False).stdout.split()
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(pid), signal.SIGKILL)


class NetLab(Closing):
    """Hosts in network namespaces on one bridge; context manager, `close()` safe twice."""

    def __init__(self, hosts: Sequence[str], *, subnet: str = "10.77.0") -> None:
        if not 1 <= len(hosts) <= 200:
            raise ValueError(f"1 to 200 hosts, got {len(hosts)}")
        self.hosts = tuple(hosts)
        self.subnet = subnet
        self.tag = f"{PREFIX}{os.getpid()}x{next(_counter)}"
        self.switch = f"{self.tag}-sw"
        self._made: list[str] = []
        self._closed = False

    def namespace(self, host: str) -> str:
        """The network namespace of `host`."""
        return f"{self.tag}-{self.hosts.index(host)}"

    def address(self, host: str) -> str:
        """The IPv4 address of `host` on the lab's bridge."""
        return f"{self.subnet}.{self.hosts.index(host) + 1}"

    def open(self) -> Self:
        """Make the namespaces and links (everything made is removed if a step fails)."""
        reap_stale()
        try:
            self._namespace(self.switch)
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.switch, "link", "set", "br0", "up")
            for host in self.hosts:
                self._host(host)
        except (OSError, subprocess.SubprocessError):
            self.close()
            raise
        return self

    def _namespace(self, name: str) -> None:
        _ip("netns", "add", name)
        self._made.append(name)
        _ip("-n", name, "link", "set", "lo", "up")
        ipv4_only = ["net.ipv6.conf.all.disable_ipv6=1", "net.ipv6.conf.default.disable_ipv6=1"]
        _ip("netns", "exec", name, "sysctl", "-qw", *ipv4_only, check=False)

    def _port(self, host: str) -> str:
        return f"p{self.hosts.index(host)}"

    def _host(self, host: str) -> None:
        ns, port = self.namespace(host), self._port(host)
        self._namespace(ns)
        _ip(
            "link",
            "add",
            "eth0",
            "netns",
            ns,
            "type",
            "veth",
            "peer",
            "name",
            port,
            "netns",
            self.switch,
        )
        _ip("-n", self.switch, "link", "set", port, "master", "br0")
        _ip("-n", self.switch, "link", "set", port, "up")
        _ip("-n", ns, "addr", "add", f"{self.address(host)}/24", "dev", "eth0")
        _ip("-n", ns, "link", "set", "eth0", "up")

    def set_link(self, host: str, *, up: bool) -> None:
        """Plug (`up`) or pull `host`'s cable at the switch."""
        _ip("-n", self.switch, "link", "set", self._port(host), "up" if up else "down")

    def command(self, host: str, argv: Sequence[str]) -> list[str]:
        """`argv` run inside `host`'s namespace."""
        return [_ip_path(), "netns", "exec", self.namespace(host), *argv]

    def popen(self, host: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Start `argv` inside `host`'s namespace."""
        return subprocess.Popen(self.command(host, argv), **kwargs)

    def close(self) -> None:
        """Kill what still runs inside and delete every namespace; safe twice."""
        if self._closed:
            return
        self._closed = True
        for name in reversed(self._made):
            _kill_inside(name)
            _ip("netns", "del", name, check=False)
        self._made.clear()

    def __enter__(self) -> Self:
        return self.open()


# --- the observer -------------------------------------------------------------------------


def observe(fleet: str, connect: str, seconds: float) -> None:
    """Print a fleet's sense frames, states and liveliness as JSON lines, for `seconds`."""
    from phalanx.wire.keys import alive_pattern, robots_key
    from phalanx.wire.messages import RobotState, SenseFrame
    from phalanx.wire.transport import TransportConfig, open_session

    lines: queue.SimpleQueue[str] = queue.SimpleQueue()

    def put(**record: object) -> None:
        lines.put(json.dumps({"t": time.monotonic(), **record}))

    def on_sense(_key: str, frame: SenseFrame) -> None:
        put(kind="sense", robot=frame.robot_id, v=frame.v_mps, tick=frame.tick)

    def on_state(_key: str, state: RobotState) -> None:
        put(
            kind="state",
            robot=state.robot_id,
            fsm=state.fsm_state,
            seq=state.seq,
            stamp=state.stamp_s,
        )

    def on_alive(key: str, alive: bool) -> None:
        put(kind="alive", robot=key.rsplit("/", 1)[-1], alive=alive)

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with open_session(TransportConfig(mode="client", connect=(connect,))) as session:
        session.subscribe(robots_key(fleet, "sense"), SenseFrame, on_sense)
        session.subscribe(robots_key(fleet, "state"), RobotState, on_state)
        session.watch_alive(alive_pattern(fleet), on_alive)
        put(kind="ready")
        deadline = time.monotonic() + seconds
        while not stop.is_set() and time.monotonic() < deadline:
            _flush(lines)
            stop.wait(0.02)
        _flush(lines)


def _flush(lines: queue.SimpleQueue[str]) -> None:
    with contextlib.suppress(BrokenPipeError):
        while not lines.empty():
            sys.stdout.write(lines.get() + "\n")
        sys.stdout.flush()


def main(argv: Sequence[str] | None = None) -> None:
    """`python netlab.py observe ...`."""
    parser = argparse.ArgumentParser(prog="netlab.py")
    sub = parser.add_subparsers(dest="command", required=True)
    watch = sub.add_parser("observe", help="print a fleet's frames, states and liveliness")
    watch.add_argument("--fleet", required=True)
    watch.add_argument("--connect", required=True)
    watch.add_argument("--seconds", type=float, default=600.0)
    args = parser.parse_args(argv)
    observe(args.fleet, args.connect, args.seconds)


if __name__ == "__main__":
    main()
