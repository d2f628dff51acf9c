"""Navigation: how the robot that leads finds the group's way, and how a follower finds
its own round what the shape does not clear. The rest of the brain imports what it uses
from here.

- `plan`: what a leader does (`Plan`): its script, go to waypoints, or wander;
- `grid`: the occupancy grid a robot's sonar fills (`OccupancyMap`), and the route over
  it (a wavefront, obstacles grown by a clearance);
- `fleet_map`: the fleet's shared grid, fed by every robot's scans (`FleetMap`);
- `route`: where to head for next on the way to a waypoint, re-planned as the map grows
  (`RoutePlanner`);
- `clearance`: the free way along every candidate heading, for the robot alone or the
  whole shape (`Clearances`);
- `steering`: the heading to take round obstacles and the twist that takes it (`steer`),
  kept to what the rigid shape's slots can follow; the navigator's memories;
- `deadlock`: getting out of a dead end: the stall watch, the reverse straight back,
  along the arc just driven or along the path it came (`reverse_twist`, `Breadcrumbs`);
- `column_path`: the path the robot ahead drove, which a column's follower keeps to
  (`Trail`);
- `settings`: what navigation reads of a scenario (`NavSettings`);
- `warm`: the compiled kernels made ready before a real-time loop (`warm_kernels`).

No I/O; the behaviours (`phalanx.agents.behaviours`) drive with these.
"""

from __future__ import annotations

from phalanx.agents.navigation.clearance import (
    HEADINGS_RAD,
    Clearances,
    clearance_along,
    corridor_clearance,
    heading_index,
    open_side,
)
from phalanx.agents.navigation.column_path import Trail
from phalanx.agents.navigation.deadlock import (
    Breadcrumbs,
    Course,
    StallWatch,
    free_heading_near,
    reverse_twist,
)
from phalanx.agents.navigation.fleet_map import FleetMap
from phalanx.agents.navigation.grid import OccupancyMap
from phalanx.agents.navigation.plan import Plan, ScriptedProfile, WanderHeading, plan_of
from phalanx.agents.navigation.route import ROUTE_AHEAD_M, RoutePlanner
from phalanx.agents.navigation.settings import NavSettings
from phalanx.agents.navigation.steering import (
    REORIENT_RAD,
    RecentEchoes,
    Steering,
    bearing_rad,
    centring_rad,
    rigid_limit,
    steer,
    turn_rate_radps,
)
from phalanx.agents.navigation.warm import warm_kernels

__all__ = [
    "HEADINGS_RAD",
    "REORIENT_RAD",
    "ROUTE_AHEAD_M",
    "Breadcrumbs",
    "Clearances",
    "Course",
    "FleetMap",
    "NavSettings",
    "OccupancyMap",
    "Plan",
    "RecentEchoes",
    "RoutePlanner",
    "ScriptedProfile",
    "StallWatch",
    "Steering",
    "Trail",
    "WanderHeading",
    "bearing_rad",
    "centring_rad",
    "clearance_along",
    "corridor_clearance",
    "free_heading_near",
    "heading_index",
    "open_side",
    "plan_of",
    "reverse_twist",
    "rigid_limit",
    "steer",
    "turn_rate_radps",
    "warm_kernels",
]
