"""The garbage collector during a run's loop.

What exists when a loop starts (the modules, the fleet, the world, the Zenoh session,
the traces) lives as long as the loop. Left to itself, Python's collector traverses all
of it at each full pass; frozen (`gc.freeze`), its passes see only what the loop itself
made, so a pass costs what the loop's own objects cost, and a step that a pass lands in
is that much shorter (docs/PERFORMANCE.md, "The collector in an agent's loop": 12-20 ms
for a full pass over an agent process's heap as it is).
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def lifelong_heap() -> Iterator[None]:
    """Freeze what exists now for the `with` block (a run's loop), and let it go after,
    however the block ends. The freeze is the whole process's: a loop that ends lets go
    of everything, also what another loop running meanwhile (in a thread) had frozen,
    which then runs on with its heap as it is; so what a finished run leaves in
    reference cycles is collected after it, also in a process that runs one run after
    another in several threads (a sweep's worker).
    """
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
