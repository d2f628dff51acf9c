"""docs/RESULTS.md's generated parts: `phalanx report` rewrites the paper matrix and keeps
the sections the benchmarks write between their markers, in order."""

from __future__ import annotations

from phalanx.analysis.report import (
    LOCALISATION_BEGIN,
    LOCALISATION_END,
    NOTES_BEGIN,
    NOTES_END,
    SECTION_BEGIN,
    SECTION_END,
    SWEEP_BEGIN,
    SWEEP_END,
    keep_sections,
    with_section,
)

NAV = f"{SECTION_BEGIN}\n## Navigation\nnav table\n{SECTION_END}"
LOC = f"{LOCALISATION_BEGIN}\n## Real sensing\nsensing table\n{LOCALISATION_END}"


def test_the_report_keeps_both_benchmark_sections() -> None:
    old = f"# Results\nold matrix\n\n{NAV}\n\n{LOC}\n"
    new = keep_sections("# Results\nnew matrix\n", old)
    assert "new matrix" in new
    assert "old matrix" not in new
    assert new.index(NAV) < new.index(LOC)


def test_each_benchmark_rewrites_only_its_own_section() -> None:
    text = f"# Results\nmatrix\n\n{NAV}\n"
    with_loc = with_section(text, LOC, begin=LOCALISATION_BEGIN, end=LOCALISATION_END)
    assert with_loc.endswith(LOC + "\n")
    newer = LOC.replace("sensing table", "sensing table v2")
    again = with_section(with_loc, newer, begin=LOCALISATION_BEGIN, end=LOCALISATION_END)
    assert "sensing table v2" in again
    assert again.count(LOCALISATION_BEGIN) == 1
    assert NAV in again
    nav2 = NAV.replace("nav table", "nav table v2")
    assert "nav table v2" in with_section(again, nav2)
    assert "sensing table v2" in with_section(again, nav2)


def test_the_sweep_notes_outlive_the_report_and_a_new_sweep() -> None:
    sweep = f"{SWEEP_BEGIN}\n## Sweep\nsweep table\n{SWEEP_END}"
    notes = f"{NOTES_BEGIN}\nwhat the table means\n{NOTES_END}"
    old = f"# Results\nold matrix\n\n{NAV}\n\n{sweep}\n\n{notes}\n\n{LOC}\n"
    new = keep_sections("# Results\nnew matrix\n", old)
    assert new.index(sweep) < new.index(notes) < new.index(LOC)
    rewritten = with_section(
        new, sweep.replace("sweep table", "sweep table v2"), begin=SWEEP_BEGIN, end=SWEEP_END
    )
    assert "sweep table v2" in rewritten
    assert notes in rewritten
