"""What a compiled kernel (numba) would cost and give a fresh phalanx process.

The 3-robot row of `bench_vs_irsim.py` is whole-process time: a kernel helps it only if
what a fresh process pays before its first step (importing numba, loading the compiled
kernel from numba's on-disk cache) is smaller than what the kernel saves over the run.
This measures both, in fresh processes with the kernel's cache already written (the
first, compiling run is printed apart):

- start-up: importing numpy, importing numba and the kernel, the kernel's first call;
- the step's ray casting for 3 robots (144 rays against 16 discs, every pair, nearest
  per ray) by the kernel and by `phalanx.simulator.sonar.ray_circle_hits`, and whether
  the two agree to the last bit (the same arithmetic, in the same order);
- how often numba's arctan2 and cos differ from numpy's on random input (what sensing
  uses for bearings and ray directions, so what a kernel would have to leave to numpy).

numba comes with the dev, sweep and fast extras (`phalanx.core.compiled`).

    .venv/bin/python bench/probe_numba.py [--runs 3]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench_vs_irsim import run
from calibration import Calibration, load

KERNEL = """
import numba
import numpy as np


@numba.njit(cache=True)
def nearest_hits(ox, oy, dx, dy, cx, cy, r, out):
    for i in range(ox.size):
        best = np.inf
        for j in range(cx.size):
            fx = ox[i] - cx[j]
            fy = oy[i] - cy[j]
            b = fx * dx[i] + fy * dy[i]
            c = fx * fx + fy * fy - r[j] * r[j]
            disc = b * b - c
            if disc >= 0.0:
                root = np.sqrt(max(disc, 0.0))
                t = -b - root
                if t < 0.0:
                    t = 0.0 if -b + root >= 0.0 else np.inf
                best = min(best, t)
        out[i] = best


@numba.njit(cache=True)
def atan2_cos(y, x, out_atan2, out_cos):
    for i in range(y.size):
        out_atan2[i] = np.arctan2(y[i], x[i])
        out_cos[i] = np.cos(y[i])
"""

CHILD = """
import json, sys, time
t0 = time.perf_counter()
import numpy as np
t1 = time.perf_counter()
rng = np.random.default_rng(3)
rays, discs = 144, 16
ox, oy = rng.uniform(-3.0, 3.0, rays), rng.uniform(-3.0, 3.0, rays)
heading = rng.uniform(-np.pi, np.pi, rays)
dx, dy = np.cos(heading), np.sin(heading)
cx, cy = rng.uniform(-5.0, 5.0, discs), rng.uniform(-5.0, 5.0, discs)
r = rng.uniform(0.2, 0.4, discs)
out = np.empty(rays)
t1b = time.perf_counter()
sys.path.insert(0, json.loads(sys.argv[1])[0])
import kernel
t2 = time.perf_counter()
kernel.nearest_hits(ox, oy, dx, dy, cx, cy, r, out)
t3 = time.perf_counter()
from phalanx.simulator.sonar import ray_circle_hits
reference = ray_circle_hits(ox, oy, dx, dy, cx, cy, r)
def per_call(fn, calls=3000):
    started = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - started) / calls
compiled_s = per_call(lambda: kernel.nearest_hits(ox, oy, dx, dy, cx, cy, r, out))
numpy_s = per_call(lambda: ray_circle_hits(ox, oy, dx, dy, cx, cy, r))
y, x = rng.uniform(-10.0, 10.0, 100_000), rng.uniform(-10.0, 10.0, 100_000)
a, c = np.empty_like(y), np.empty_like(y)
kernel.atan2_cos(y, x, a, c)
print(json.dumps({
    "numpy_import_s": t1 - t0, "numba_import_s": t2 - t1b, "first_call_s": t3 - t2,
    "compiled_s": compiled_s, "numpy_s": numpy_s,
    "same_bits": bool(np.array_equal(out, reference)),
    "atan2_differs": float(np.mean(a != np.arctan2(y, x))),
    "cos_differs": float(np.mean(c != np.cos(y))),
}))
"""


def run_child(folder: Path) -> tuple[float, dict[str, Any]]:
    """(whole process wall s, what it printed) of one fresh process using the kernel."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(folder / "cache")}
    return run(CHILD, [str(folder)], env=env)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    if importlib.util.find_spec("numba") is None:
        sys.exit("numba is not installed (not a phalanx dependency): .venv/bin/pip install numba")
    cal = Calibration.measure()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "kernel.py").write_text(KERNEL, encoding="utf-8")
        whole, _ = run_child(folder)
        print(f"first run (compiles, writes the cache): whole process {whole:.2f} s")
        runs = [run_child(folder) for _ in range(args.runs)]
    med = {k: statistics.median(out[k] for _, out in runs) for k in runs[0][1]}
    startup = med["numba_import_s"] + med["first_call_s"]
    print(
        f"cached runs (median of {args.runs}), load {load()}:\n"
        f"  import numpy {1e3 * med['numpy_import_s']:.0f} ms, import numba and the kernel "
        f"{1e3 * med['numba_import_s']:.0f} ms, first call {1e3 * med['first_call_s']:.0f} ms"
        f" -> numba's start-up {1e3 * startup:.0f} ms ({cal.cal(startup)})\n"
        f"  3 robots' cast, 144 rays x 16 discs: kernel {1e6 * med['compiled_s']:.1f} us, "
        f"ray_circle_hits {1e6 * med['numpy_s']:.1f} us; same bits: "
        f"{all(out['same_bits'] for _, out in runs)}\n"
        f"  numba's results differing from numpy's on 100 000 random inputs: arctan2 "
        f"{100 * med['atan2_differs']:.1f} %, cos {100 * med['cos_differs']:.1f} %\n"
        f"  whole process (median) {statistics.median(w for w, _ in runs):.2f} s"
    )


if __name__ == "__main__":
    main()
