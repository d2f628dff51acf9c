"""The `[localisation]` table of a scenario: whether each robot runs the pose estimator,
the wheel odometry's errors, and which positioning sources each robot has, with their
noise. The same figures drive the simulated sensors (`phalanx.simulator.sensors`) and the
estimator's noise model (`phalanx.agents.estimation`): a simulated run is told the truth
about its sensors, a real one is told what its sensors' datasheets and calibration say.

The paper's scenarios leave it out: perfect sensing, no estimator, every robot steering
from its odometry as the world gives it (bit for bit what they always did).
"""

from __future__ import annotations

import math
from typing import Annotated, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from phalanx.core.quantities import Angle, BodyOffset, Fraction, Length

RobotId = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]{1,32}$")]
# A camera's image coordinates (px): its size's bound, either side of the image.
Pixels = Annotated[float, Field(ge=-20000.0, le=20000.0)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class OdometryErrors(_Model):
    """Wheel odometry's errors, per wheel: a scale error drawn once per robot (a tyre a
    little larger than nominal: std as a fraction of the travel), a random walk (std of
    the travel error after 1 m, growing with the square root of the distance), and
    occasional slip (events per metre a wheel travels; a slipping wheel loses up to
    `slip_max_frac` of that step's travel). The estimator's process noise follows from
    them, never below `floor_std_m` / `floor_std_deg` per second.
    """

    scale_std_frac: Annotated[float, Field(ge=0.0, le=0.2)] = 0.0
    walk_std_m: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0
    slip_per_m: Annotated[float, Field(ge=0.0, le=100.0)] = 0.0
    slip_max_frac: Fraction = 0.3
    floor_std_m: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0001
    floor_std_deg: Annotated[float, Field(ge=0.0, le=45.0)] = 0.01

    @property
    def any(self) -> bool:
        """Whether the odometry has any error at all."""
        return self.scale_std_frac > 0.0 or self.walk_std_m > 0.0 or self.slip_per_m > 0.0


class MocapSource(_Model):
    """External positioning (motion capture, an overhead camera, UWB): absolute pose fixes
    at `rate_hz`, `latency_s` old when they arrive, with `std_m` on x and y and `std_deg`
    on the heading, a share `dropout` of them lost. `bodies` maps the system's rigid-body
    names to robot ids (a robot without an entry is tracked under its own id); `robots`
    limits the source to some robots (empty: every robot). The estimator fuses at most
    `fuse_hz` of them a second (each at its own time; the rest are counted, not used).
    `stamp_std_s`: how far a fix's stamp may be off the timeline of the robot's odometry
    (the system's latency is known only so well; a driver stamps a reading when it
    reaches the computer, which a loaded computer does late): the estimator counts a fix
    uncertain by as far as the robot moves in that time.
    """

    rate_hz: Annotated[float, Field(gt=0.0, le=1000.0)] = 100.0
    latency_s: Annotated[float, Field(ge=0.0, le=1.0)] = 0.02
    std_m: Annotated[float, Field(gt=0.0, le=1.0)] = 0.002
    std_deg: Annotated[float, Field(gt=0.0, le=45.0)] = 0.1
    dropout: Fraction = 0.01
    fuse_hz: Annotated[float, Field(gt=0.0, le=1000.0)] = 50.0
    stamp_std_s: Annotated[float, Field(ge=0.0, le=1.0)] = 0.02
    robots: tuple[RobotId, ...] = ()
    bodies: dict[str, RobotId] = Field(default_factory=dict)

    def tracks(self, robot_id: str) -> bool:
        """Whether `robot_id` gets fixes from this source."""
        return not self.robots or robot_id in self.robots

    def body_of(self, robot_id: str) -> str:
        """The rigid-body name the system tracks `robot_id` under."""
        return next((name for name, rid in self.bodies.items() if rid == robot_id), robot_id)


class MarkerSource(_Model):
    """Relative sensing of the robot a follower tracks: a camera reading the fiducial
    marker on it (range, bearing and relative heading) at `rate_hz`, `latency_s` late,
    noise growing with range (`range_std_frac` of the range; `bearing_std_deg`, and
    `heading_std_deg` times range over 1 m, at least that), a `fov_deg` field of view
    about the camera's axis, `min_range_m` to `max_range_m`, occluded by robots and
    obstacles. The camera points at `mount_yaw_deg[robot]` from the robot's heading, or,
    for a robot not listed there, at where the robot it tracks sits in the formation.
    `robots`: robots with a camera (empty: every robot that follows in the formation).
    """

    rate_hz: Annotated[float, Field(gt=0.0, le=240.0)] = 15.0
    latency_s: Annotated[float, Field(ge=0.0, le=1.0)] = 0.05
    range_std_frac: Annotated[float, Field(gt=0.0, le=1.0)] = 0.02
    bearing_std_deg: Annotated[float, Field(gt=0.0, le=45.0)] = 1.0
    heading_std_deg: Annotated[float, Field(gt=0.0, le=45.0)] = 1.0
    fov_deg: Annotated[float, Field(gt=0.0, le=360.0)] = 90.0
    min_range_m: Annotated[float, Field(ge=0.0, le=50.0)] = 0.3
    max_range_m: Annotated[float, Field(gt=0.0, le=50.0)] = 5.0
    dropout: Fraction = 0.0
    robots: tuple[RobotId, ...] = ()
    mount_yaw_deg: dict[RobotId, Angle] = Field(default_factory=dict)
    # A real camera (`phalanx.drivers.markers`): the marker family, its printed side (m),
    # which robot each marker id is on (unlisted: the robot's index in the scenario) and
    # which way its face looks (deg from that robot's heading; 180: on its back, facing
    # the robots behind), and how far behind its face the robot's centre is (m).
    dictionary: str = Field(default="DICT_APRILTAG_36h11", pattern=r"^DICT_[A-Z0-9_a-z]+$")
    marker_size_m: Annotated[float, Field(gt=0.0, le=2.0)] = 0.16
    marker_ids: dict[int, RobotId] = Field(default_factory=dict)
    face_deg: dict[int, Angle] = Field(default_factory=dict)
    marker_depth_m: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0

    @model_validator(mode="after")
    def _ranges(self) -> Self:
        if self.min_range_m >= self.max_range_m:
            raise ValueError("min_range_m must be below max_range_m")
        return self

    @property
    def half_fov_rad(self) -> float:
        """Half the field of view, rad."""
        return math.radians(self.fov_deg) / 2


class LocalisationConfig(_Model):
    """Pose estimation on every robot and the sources it fuses (see the module's doc).

    `estimator`: each robot runs the filter and steers from its estimate, publishing the
    estimate's covariance; off, it steers from its odometry as given (perfect sensing).
    `initial_std_m` / `initial_std_deg`: how well a robot knows its start pose.
    `history_s`: how late a measurement may come and still be applied at its own time.
    `gate`: Mahalanobis distance squared beyond which a measurement is rejected (counted).
    """

    estimator: bool = False
    odometry: OdometryErrors = OdometryErrors()
    mocap: MocapSource | None = None
    markers: MarkerSource | None = None
    initial_std_m: Length = 0.01
    initial_std_deg: Annotated[float, Field(ge=0.0, le=180.0)] = 1.0
    history_s: Annotated[float, Field(gt=0.0, le=10.0)] = 1.0
    gate: Annotated[float, Field(gt=0.0, le=1e4)] = 25.0

    @model_validator(mode="after")
    def _sources_need_the_estimator(self) -> Self:
        if (self.mocap is not None or self.markers is not None) and not self.estimator:
            raise ValueError("positioning sources need `estimator = true`")
        return self


class CameraCalibration(_Model):
    """A pinhole camera's calibration (`--camera-calibration FILE`, TOML): focal lengths
    and principal point in pixels, OpenCV's distortion coefficients (k1, k2, p1, p2[, k3]),
    the image size; and where it sits on the robot (m, deg from the robot's heading).
    """

    width_px: Annotated[int, Field(gt=0, le=20000)]
    height_px: Annotated[int, Field(gt=0, le=20000)]
    fx_px: Annotated[float, Field(gt=0.0, le=1e6)]
    fy_px: Annotated[float, Field(gt=0.0, le=1e6)]
    cx_px: Pixels
    cy_px: Pixels
    distortion: tuple[Annotated[float, Field(ge=-1e6, le=1e6)], ...] = Field(
        default=(), max_length=8
    )
    mount_x_m: BodyOffset = 0.0
    mount_y_m: BodyOffset = 0.0
    mount_yaw_deg: Angle = 0.0

    @model_validator(mode="after")
    def _known_distortion(self) -> Self:
        if len(self.distortion) not in (0, 4, 5, 8):
            raise ValueError("distortion: give 0, 4, 5 or 8 coefficients (OpenCV's order)")
        return self
