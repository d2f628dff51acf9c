"""What a run's figure files are called and in which formats they come, apart from the
drawing (`phalanx.analysis.figures`): naming them does not load matplotlib, so a run
without figures, and the command line, never do.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, get_args

FigureFormat = Literal["png", "pdf", "svg"]
FORMATS: tuple[FigureFormat, ...] = get_args(FigureFormat)
DEFAULT_DPI = 150
# Pixel density bounds: below is unreadable, above costs seconds and tens of megabytes.
DPI_MIN, DPI_MAX = 50, 600
# The paper's figures 4b, 5, 6 and 7, in that order (`figures.FIGURES` draws them).
FIGURE_FILES = (
    "fig4b_states.png",
    "fig5_trajectories.png",
    "fig6_separations.png",
    "fig7_velocities.png",
)
PAPER_FIGURE = "paper.pdf"
ESTIMATION_FIGURE = "estimation.png"


def figure_name(name: str, fmt: FigureFormat) -> str:
    """The file name of figure `name` (one of FIGURE_FILES) in format `fmt`."""
    return str(Path(name).with_suffix(f".{fmt}"))
