"""Fiducial markers read from camera images rendered with a pinhole model at known poses:
the relative pose comes back within stated tolerances, and no marker gives nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from phalanx.core.geometry import Pose2D
from phalanx.core.localisation import CameraCalibration, MarkerSource

cv2 = pytest.importorskip("cv2", reason="marker detection needs the sensing extra (OpenCV)")

from phalanx.drivers.markers import MarkerDetector  # noqa: E402
from phalanx.simulator.sensors.render import marker_card, render_view  # noqa: E402

# 1280 x 960, 77 deg across; a 20 cm AprilTag 36h11
CAMERA = CameraCalibration(width_px=1280, height_px=960, fx_px=800.0, fy_px=800.0,
                           cx_px=640.0, cy_px=480.0)  # fmt: skip
SOURCE = MarkerSource(marker_size_m=0.2)
IDS = ("r1", "r2", "r3")
RANGE_TOLERANCE = 0.02  # share of the range (the noise the scenarios give markers)
BEARING_TOLERANCE_RAD = math.radians(0.2)
HEADING_TOLERANCE_RAD = math.radians(3.0)


def _view(viewer: Pose2D, rng: float, bearing: float, heading: float, *, marker: int = 0,
          camera: CameraCalibration = CAMERA, noise: float = 0.0) -> np.ndarray:  # fmt: skip
    th = viewer.theta_rad + bearing
    target = Pose2D(viewer.x_m + rng * math.cos(th), viewer.y_m + rng * math.sin(th),
                    viewer.theta_rad + heading)  # fmt: skip
    card = marker_card(SOURCE.dictionary, marker)
    return render_view(camera, viewer, target, card=card, marker_size_m=SOURCE.marker_size_m,
                       noise_std=noise)  # fmt: skip


POSES = [
    (r, b, h) for r in (0.6, 1.0, 2.0, 3.0) for b in (-0.45, 0.0, 0.3) for h in (-0.6, 0.0, 0.4)
]


def test_the_relative_pose_at_known_poses() -> None:
    detector = MarkerDetector(CAMERA, SOURCE, robot_ids=IDS, own_id="r2")
    viewer = Pose2D(3.0, -1.0, 0.7)
    headings = 0
    for rng, bearing, heading in POSES:
        fixes = detector.detect(_view(viewer, rng, bearing, heading, noise=2.0), stamp_s=12.5)
        assert len(fixes) == 1, (rng, bearing, heading)
        fix = fixes[0]
        assert (fix.target_id, fix.stamp_s) == ("r1", 12.5)
        assert fix.range_m == pytest.approx(rng, rel=RANGE_TOLERANCE), (rng, bearing, heading)
        assert fix.bearing_rad == pytest.approx(bearing, abs=BEARING_TOLERANCE_RAD)
        if fix.heading_rad is not None:  # left out when two poses project alike
            headings += 1
            assert fix.heading_rad == pytest.approx(heading, abs=HEADING_TOLERANCE_RAD), (
                rng, bearing, heading,
            )  # fmt: skip
    assert headings >= 0.75 * len(POSES)


def test_the_camera_mount_turns_the_bearing() -> None:
    turned = CAMERA.model_copy(update={"mount_yaw_deg": 40.0, "mount_x_m": 0.1})
    detector = MarkerDetector(turned, SOURCE, robot_ids=IDS, own_id="r2")
    viewer = Pose2D(0.0, 0.0, 0.0)
    image = _view(viewer, 1.5, math.radians(45.0), 0.2, camera=turned)
    (fix,) = detector.detect(image, 0.0)
    assert fix.bearing_rad == pytest.approx(math.radians(45.0), abs=BEARING_TOLERANCE_RAD)
    assert fix.range_m == pytest.approx(1.5, rel=RANGE_TOLERANCE)


def test_no_marker_no_measurement() -> None:
    detector = MarkerDetector(CAMERA, SOURCE, robot_ids=IDS, own_id="r2")
    viewer = Pose2D(0.0, 0.0, 0.0)
    behind = _view(viewer, 1.5, math.pi, 0.0)  # the robot is behind the camera
    assert detector.detect(behind, 0.0) == []
    blank = np.full((CAMERA.height_px, CAMERA.width_px), 110, dtype=np.uint8)
    assert detector.detect(blank, 0.0) == []
    # its own marker (id 1 is r2's) and one nobody carries give nothing either
    assert detector.detect(_view(viewer, 1.0, 0.0, 0.0, marker=1), 0.0) == []
    assert detector.detect(_view(viewer, 1.0, 0.0, 0.0, marker=17), 0.0) == []
    assert detector.unknown == 2
