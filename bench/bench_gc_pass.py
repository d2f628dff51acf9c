"""What the garbage collector costs a follower's loop, with and without the heap frozen.

Builds the follower of `bench_step_cold.py` (`g1` of a 10-robot grid, hearing its
formation) with an agent process's modules loaded (Zenoh's, the runtime's), steps it
`--warmup` times, then prints:

- how many objects the collector tracks, and how long a full pass over them takes
  (median of 20), with the heap as it is and frozen (`phalanx.runtime.heap`);
- over `--steps` steps each way, the collections of each generation and the time they
  took (what lands in steps: `gc.callbacks`).

    .venv/bin/python bench/bench_gc_pass.py [--steps 2000] [--warmup 100]
"""

from __future__ import annotations

import argparse
import gc
import statistics
import time
from collections.abc import Callable

import zenoh  # noqa: F401  (an agent process has its session's module loaded)
from bench_step_cold import follower
from calibration import Calibration

from phalanx.runtime import agent  # noqa: F401  (and the runtime's)
from phalanx.runtime.heap import lifelong_heap


def full_pass_ms() -> float:
    """One full collection's wall time (ms)."""
    started = time.perf_counter()
    gc.collect()
    return 1e3 * (time.perf_counter() - started)


def collections(step: Callable[[int], float], first: int, steps: int) -> list[tuple[int, float]]:
    """Per generation, the collections in `steps` steps from `first` on and their time (ms)."""
    counts = [0, 0, 0]
    spent = [0.0, 0.0, 0.0]
    began: dict[int, float] = {}

    def watch(phase: str, info: dict[str, int]) -> None:
        generation = info["generation"]
        if phase == "start":
            began[generation] = time.perf_counter()
        else:
            counts[generation] += 1
            spent[generation] += 1e3 * (time.perf_counter() - began[generation])

    gc.callbacks.append(watch)
    try:
        for k in range(first, first + steps):
            step(k)
    finally:
        gc.callbacks.remove(watch)
    return list(zip(counts, spent, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--warmup", type=int, default=100)
    args = parser.parse_args()
    cal = Calibration.measure()
    step = follower("formation")
    for k in range(args.warmup):
        step(k)
    print(f"objects the collector tracks: {len(gc.get_objects())}")
    plain = statistics.median(full_pass_ms() for _ in range(20))
    with lifelong_heap():
        frozen = statistics.median(full_pass_ms() for _ in range(20))
    print(
        f"a full pass: {plain:.2f} ms ({1e3 * cal.ratio(plain / 1e3):.0f} mcal) as it is, "
        f"{frozen:.3f} ms frozen"
    )
    first = args.warmup
    rows = [("as it is", collections(step, first, args.steps))]
    with lifelong_heap():
        rows.append(("frozen", collections(step, first + args.steps, args.steps)))
    print(f"over {args.steps} steps: collections (ms) of generation 0 / 1 / 2")
    for label, gens in rows:
        print(f"  {label:9s} " + " / ".join(f"{n} ({ms:.2f})" for n, ms in gens))
    Calibration.measure()


if __name__ == "__main__":
    main()
