"""The fuzz campaign of docs/RELIABILITY.md: for every key a process subscribes to, the
boundary sweep (every field at each boundary value of its type) and then `--per-key`
hostile payloads from hypothesis strategies built from the wire models (random,
truncated, bit-flipped, schema-shaped extreme and perturbed), each into the real
receiving code (`lab/receivers.py`: the agent in real time and in lockstep, the
world, a host daemon, the launcher), each followed by a step of that process; its
commands held to the run's limits, its log, metrics and status written, every few.

Prints one row per key: payloads sent, crashes (0, or the first failing payload), what
the receiver counted as dropped, and the time taken. The same fuzzers run in CI with a
bounded sample (`tests/faults/test_fuzz_keys.py`).

    .venv/bin/python bench/bench_fuzz.py                    # 10^5 per key, 2 workers
    .venv/bin/python bench/bench_fuzz.py --per-key 2000 --workers 1 --keys agent/sense
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "lab"))

KEYS = [
    ("realtime", "agent/flags"),
    ("realtime", "agent/state"),
    ("realtime", "agent/sense"),
    ("realtime", "agent/operator"),
    ("navigating", "agent/scan"),
    ("driver", "agent/fix"),
    ("driver", "agent/relative"),
    ("lockstep", "agent/sense"),
    ("realtime", "world/cmd"),
    (None, "world/state"),
    (None, "world/event"),
    (None, "world/report"),
    (None, "world/leader"),
    (None, "daemon/spawn"),
    (None, "daemon/stop"),
    (None, "daemon/status"),
    (None, "launcher/state"),
    (None, "launcher/log"),
    (None, "launcher/reply"),
]


def run_key(clock: str | None, key: str, per_key: int, seed: int) -> dict[str, Any]:
    """Sweep and campaign on one key, in a fresh receiver; the row."""
    import logging

    from receivers import (
        AgentUnderTest,
        DaemonUnderTest,
        DriverAgentUnderTest,
        LauncherUnderTest,
        WorldUnderTest,
        campaign,
        sweep,
    )

    logging.disable(logging.WARNING)  # a refused request logs a line: millions of them here
    warnings.simplefilter("error")  # as the test suite does: a warning is a failure
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        kind = key.split("/")[0]
        receiver: Any
        if clock == "driver":
            receiver = DriverAgentUnderTest()
        elif clock == "navigating":
            receiver = AgentUnderTest(navigating=True)
        elif kind == "agent":
            receiver = AgentUnderTest(clock=clock or "realtime")
        elif kind == "world":
            receiver = WorldUnderTest(clock=clock or "lockstep")
        elif kind == "daemon":
            receiver = DaemonUnderTest(Path(tmp))
        else:
            receiver = LauncherUnderTest()
        row: dict[str, Any] = {"key": key if clock is None else f"{key} ({clock})"}
        try:
            swept = sweep(receiver, key, check_every=500)
            sent = campaign(receiver, key, per_key, seed=seed, check_every=500)
            row.update(payloads=swept + sent, crashes=0, failure="")
        except AssertionError as exc:
            row.update(payloads=None, crashes=1, failure=str(exc)[:400])
        stats = getattr(getattr(receiver, "session", None), "stats", None)
        row["dropped"] = stats.dropped if stats is not None else None
        daemon = getattr(receiver, "daemon", None)
        if daemon is not None:
            row["refused"] = daemon.refused
        row["seconds"] = round(time.perf_counter() - started, 1)
        close = getattr(receiver, "close", None)
        if close is not None:
            close()
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--per-key", type=int, default=100_000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--keys", nargs="*", help="only these keys (e.g. agent/sense)")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()
    jobs = [(c, k) for c, k in KEYS if not args.keys or k in args.keys]
    rows = []
    with ProcessPoolExecutor(args.workers) as pool:
        futures = [
            pool.submit(run_key, c, k, args.per_key, args.seed + zlib.crc32(f"{k}/{c}".encode()))
            for c, k in jobs
        ]
        for future in futures:
            row = future.result()
            rows.append(row)
            print(json.dumps(row), flush=True)
    print("\n| key | payloads | crashes | dropped and counted | s |")
    print("|---|---:|---:|---:|---:|")
    for row in rows:
        dropped = row.get("refused", row["dropped"])
        print(
            f"| {row['key']} | {row['payloads']} | {row['crashes']} | {dropped} | "
            f"{row['seconds']} |"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    if any(r["crashes"] for r in rows):
        sys.exit(1)


if __name__ == "__main__":
    main()
