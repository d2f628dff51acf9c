"""The viewer's layout (the blueprint): the map with y up, one colour per robot, legends
clear of the data.

y up: Rerun's 2D views draw y downward (the image convention) and take no view
coordinates (a view's `axes` apply to 3D views only). The map is therefore drawn in a
frame of its own, `MAP_FRAME`: the root frame mirrored in y, a static transform
(`map_frame_transform`, logged at `MAP_FRAME_ENTITY` beside the blueprint). The logged
positions are unchanged; only a position read off the map's own axes (its visual
bounds, a hovered point of the view) has its y negated.

Colours: robot k of the layout has `ROBOT_COLOURS[k]` (repeating after the last) in
every view that draws it (map, time series, transitions); the bounds and limits are grey
dots, the ground truth white. They are view overrides: the recorded data keep no
colour of their own, and another layout may colour them as it likes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

Rgb = tuple[int, int, int]
Extent = tuple[float, float, float, float]  # x_min, x_max, y_min, y_max (m)

# Okabe-Ito: distinct for colour-blind eyes too, and each readable on the dark viewer.
ROBOT_COLOURS: tuple[Rgb, ...] = (
    (230, 159, 0),  # orange
    (86, 180, 233),  # sky blue
    (0, 158, 115),  # bluish green
    (240, 228, 66),  # yellow
    (213, 94, 0),  # vermillion
    (204, 121, 167),  # reddish purple
    (0, 114, 178),  # blue
)
BOUND_COLOUR: Rgb = (150, 150, 150)  # the paper's bounds and the velocity limits
TRUTH_COLOUR: Rgb = (255, 255, 255)  # ground truth, whichever robot
BOUND_MARKER_SIZE = 1.5
MEASURED_WIDTH = 2.5  # a measured or error series ...
COMMANDED_WIDTH = 1.0  # ... and the commanded one beside it, in the same colour
ERROR_AXIS = (0.0, 4.0)  # % or deg: the paper's bounds low, the legend above them

MAP_FRAME = "phalanx/map_y_up"  # the frame the map view draws in
MAP_FRAME_ENTITY = "frames/map_y_up"  # where the transform that defines it is logged
ROOT_FRAME = "tf#/"  # Rerun's implicit frame of the root entity: the world frame
MAP_FROM_ROOT = np.diag([1.0, -1.0, 1.0])  # the mirror (its own inverse)

# What each robot's map entities and time series are drawn with, by path under robots/<id>.
MAP_POINTS = ("pose", "slot_target", "estimate/xy")
MAP_STRIPS = ("trail", "sonar", "covariance")
MAP_ARROWS = ("heading",)
BOUND_PATHS = {
    "linear": ("bounds/errors/linear_pct",),
    "angular": ("bounds/errors/angular_pct",),
    "v": ("bounds/velocity/v_max_mps", "bounds/velocity/v_min_mps"),
    "omega": ("bounds/velocity/omega_max_degps", "bounds/velocity/omega_min_degps"),
}


def robot_colours(robot_ids: Sequence[str]) -> dict[str, Rgb]:
    """Each robot's colour, by its place in `robot_ids`."""
    return {rid: ROBOT_COLOURS[k % len(ROBOT_COLOURS)] for k, rid in enumerate(robot_ids)}


def map_frame_transform() -> Any:
    """The static transform that defines `MAP_FRAME`: the world mirrored in y, so that a
    2D view drawing it y-down shows the world y-up.
    """
    import rerun as rr

    return rr.Transform3D(mat3x3=MAP_FROM_ROOT, child_frame=MAP_FRAME, parent_frame=ROOT_FRAME)


def map_bounds(extent_m: Extent) -> Any:
    """The visual bounds of the map view that frame `extent_m` (world metres), in
    `MAP_FRAME`.
    """
    import rerun.blueprint as rrb

    x0, x1, y0, y1 = extent_m
    return rrb.VisualBounds2D(x_range=(x0, x1), y_range=(-y1, -y0))


def _series(colour: Rgb, name: str, width: float) -> Any:
    import rerun as rr

    return rr.SeriesLines.from_fields(colors=[colour], names=[name], widths=[width])


def _bound(name: str) -> Any:
    import rerun as rr

    return rr.SeriesPoints.from_fields(
        colors=[BOUND_COLOUR], names=[name], markers=["circle"], marker_sizes=[BOUND_MARKER_SIZE]
    )


def map_overrides(colours: Mapping[str, Rgb]) -> dict[Any, Any]:
    """Each robot's colour on every map entity it has."""
    import rerun as rr

    out: dict[Any, Any] = {}
    for rid, colour in colours.items():
        for name in MAP_POINTS:
            out[f"robots/{rid}/{name}"] = rr.Points2D.from_fields(colors=[colour])
        for name in MAP_STRIPS:
            out[f"robots/{rid}/{name}"] = rr.LineStrips2D.from_fields(colors=[colour])
        for name in MAP_ARROWS:
            out[f"robots/{rid}/{name}"] = rr.Arrows2D.from_fields(colors=[colour])
    return out


def series_overrides(
    colours: Mapping[str, Rgb], lines: Mapping[str, tuple[str, float]], bounds: Sequence[str]
) -> dict[Any, Any]:
    """A time series view's styles: `lines` (path under robots/<id> -> (legend suffix,
    width)) in each robot's colour, and the `bounds` paths as grey dots.
    """
    out: dict[Any, Any] = {}
    for rid, colour in colours.items():
        for path, (suffix, width) in lines.items():
            out[f"robots/{rid}/{path}"] = _series(colour, f"{rid} {suffix}".strip(), width)
    for path in bounds:
        out[path] = _bound("limit" if "velocity" in path else "paper bound")
    return out


def make_blueprint(robot_ids: Sequence[str], *, extent_m: Extent | None = None) -> Any:
    """Map of the fleet, error and velocity series, state log: figures 4b-7 live.

    `extent_m` (x_min, x_max, y_min, y_max, world metres) frames the map; without it
    the viewer fits it. Log `map_frame_transform()` at `MAP_FRAME_ENTITY` with it.
    """
    import rerun as rr
    import rerun.blueprint as rrb

    colours = robot_colours(robot_ids)
    whole_run = rrb.TimeAxis(
        view_range=rrb.TimeRange(
            start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()
        )
    )

    def series(
        name: str,
        lines: Mapping[str, tuple[str, float]],
        bounds: Sequence[str],
        y_range: tuple[float, float] | None,
        *,
        legend: bool,
    ) -> Any:
        contents = [f"robots/{rid}/{p}" for rid in robot_ids for p in lines]
        # The legend sits top right: above the data where the axis leaves room for it
        # (the error panels); off where the series fill the panel (the velocities, whose
        # key is in the title: the colours are the robots' everywhere).
        return rrb.TimeSeriesView(
            name=name,
            origin="/",
            contents=[*contents, *bounds],
            axis_x=whole_run,
            axis_y=rrb.ScalarAxis(range=y_range) if y_range else None,
            plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=legend),
            overrides=series_overrides(colours, lines, bounds),
        )

    one = MEASURED_WIDTH
    # The error axes stop a little above the paper's bounds (the start offsets are tens of
    # per cent and would flatten everything else); zoom out in the viewer to see them.
    errors = rrb.Tabs(
        series("linear error (%)", {"errors/linear_pct": ("", one)},
               BOUND_PATHS["linear"], ERROR_AXIS, legend=True),
        series("angular error (%)", {"errors/angular_pct": ("", one)},
               BOUND_PATHS["angular"], ERROR_AXIS, legend=True),
        series("orientation error (deg)", {"errors/orientation_deg": ("", one)}, (),
               ERROR_AXIS, legend=True),
        series("estimate (m): error thick, sigma thin",
               {"estimate/error_m": ("error", one), "estimate/std_m": ("sigma", COMMANDED_WIDTH)},
               (), None, legend=True),
    )  # fmt: skip
    twist = {"measured": ("measured", MEASURED_WIDTH), "cmd": ("commanded", COMMANDED_WIDTH)}
    states = rrb.Tabs(
        rrb.StateTimelineView(
            name="behaviour states",
            origin="/",
            contents=[f"robots/{rid}/state" for rid in robot_ids],
            time_view=whole_run,
        ),
        rrb.TextLogView(
            name="transitions",
            origin="/",
            contents=[f"robots/{rid}/fsm" for rid in robot_ids],
            overrides={
                f"robots/{rid}/fsm": rr.TextLog.from_fields(color=colour)
                for rid, colour in colours.items()
            },
        ),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(
                name="fleet map (x right, y up)",
                origin="/",
                contents=["world/**", "robots/**"],
                visual_bounds=map_bounds(extent_m) if extent_m is not None else None,
                spatial_information=rrb.SpatialInformation(target_frame=MAP_FRAME),
                overrides=map_overrides(colours),
            ),
            rrb.Vertical(
                errors,
                series(
                    "linear velocity (m/s): measured thick, commanded thin, limits dotted",
                    {f"{k}/v_mps": v for k, v in twist.items()},
                    BOUND_PATHS["v"],
                    None,
                    legend=False,
                ),
                series(
                    "yaw rate (deg/s): measured thick, commanded thin, limits dotted",
                    {f"{k}/omega_degps": v for k, v in twist.items()},
                    BOUND_PATHS["omega"],
                    None,
                    legend=False,
                ),
                states,
                row_shares=[3, 2, 2, 2],  # the error panels hold a legend: the tallest
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )
