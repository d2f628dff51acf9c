"""Reading `.rrd` recordings back (tests, reports): which entities, how many rows."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class RrdSummary:
    """Rows per entity path, the timelines seen, and the recording ids."""

    rows: Counter[str] = field(default_factory=Counter)
    timelines: frozenset[str] = frozenset()
    recording_ids: frozenset[str] = frozenset()


def summarize(path: Path) -> RrdSummary:
    """Stream every chunk of `path` (works without a footer too)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    rows: Counter[str] = Counter()
    timelines: set[str] = set()
    for chunk in reader.stream():
        rows[chunk.entity_path] += chunk.num_rows
        timelines.update(chunk.timeline_names)
    ids = frozenset(str(r) for r in _recording_ids(reader))
    return RrdSummary(rows=rows, timelines=frozenset(timelines), recording_ids=ids)


def _recording_ids(reader: object) -> list[object]:
    recordings = getattr(reader, "recordings", None)
    if recordings is None:
        return []
    return [getattr(r, "recording_id", r) for r in recordings()]
