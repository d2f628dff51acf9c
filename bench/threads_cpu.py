"""Where a multi-process run's CPU goes, by process kind and thread.

Runs a command, samples every thread of it and of its descendants from /proc four times
a second, and prints the CPU each (process kind, thread) used over a window of the run
(by default its middle, 30-60 % of the samples: past start-up, before the results).
Process kinds: `world`, `agent`, `robot` (a benchmark's multiprocessing child), `main`
(the command itself); threads: `main` (the process's main thread), `python` (other
Python threads: Zenoh's callback threads among them), and Zenoh's own by name (`rx`,
`tx`, `net`, `acc`, `app`).

    .venv/bin/python bench/threads_cpu.py [--window 0.3 0.6] -- COMMAND...
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from collections import Counter
from pathlib import Path

HZ = os.sysconf("SC_CLK_TCK")


def _tree(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except OSError:
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo += children.get(pid, [])
    return out


def _kind(pid: int) -> str:
    argv = Path(f"/proc/{pid}/cmdline").read_text().split("\0")
    if any("multiprocessing" in a for a in argv):
        return "robot"
    return next((k for k in ("world", "agent") if k in argv), "main")


def _sample(root: int) -> Counter[tuple[str, str]]:
    used: Counter[tuple[str, str]] = Counter()
    for pid in _tree(root):
        try:
            kind = _kind(pid)
            for task in Path(f"/proc/{pid}/task").iterdir():
                name = "main" if task.name == str(pid) else (task / "comm").read_text().strip()
                fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
                used[(kind, name.rstrip("0123456789-"))] += (int(fields[11]) + int(fields[12])) / HZ
        except OSError:
            continue  # a process or thread that ended while we looked
    return used


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--window", type=float, nargs=2, default=[0.3, 0.6])
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL)
    samples = []
    while proc.poll() is None:
        samples.append((time.monotonic(), _sample(proc.pid)))
        time.sleep(0.25)
    first, last = (samples[int(f * (len(samples) - 1))] for f in args.window)
    span_s = last[0] - first[0]
    used = Counter({k: v - first[1].get(k, 0.0) for k, v in last[1].items()})
    print(f"window {span_s:.2f} s: {sum(used.values()) / span_s:.2f} cores, {os.getloadavg()}")
    for (kind, thread), cpu_s in used.most_common():
        if cpu_s > 0:
            print(f"{100 * cpu_s / span_s:6.1f} % of a core  {kind:6s} {thread}")


if __name__ == "__main__":
    main()
