"""Camera images of fiducial markers rendered with a pinhole model at known poses, to test
marker detection against the truth (`phalanx.drivers.markers`): the marker, on a white
card with a quiet zone round it, at the camera's height on the target robot, projected
into the image of a camera mounted on the viewing robot. Needs OpenCV (the `sensing`
extra), imported when an image is rendered.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.geometry import Pose2D
from phalanx.core.localisation import CameraCalibration

Image = npt.NDArray[np.uint8]
CARD_MARGIN = 0.25  # white quiet zone round the marker, as a share of its side
BACKGROUND = 110  # grey level of everything else


def _cv2() -> Any:
    import cv2

    return cv2


def marker_card(dictionary: str, marker_id: int, side_px: int = 240) -> Image:
    """The printed card: the marker of `dictionary` with a white margin round it."""
    cv2 = _cv2()
    aruco = cv2.aruco
    marker = aruco.generateImageMarker(
        aruco.getPredefinedDictionary(getattr(aruco, dictionary)), marker_id, side_px
    )
    margin = round(CARD_MARGIN * side_px)
    return np.asarray(
        cv2.copyMakeBorder(marker, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255),
        dtype=np.uint8,
    )


def _camera_axes(
    calibration: CameraCalibration, viewer: Pose2D
) -> tuple[npt.NDArray[np.float64], ...]:
    c, s = math.cos(viewer.theta_rad), math.sin(viewer.theta_rad)
    origin = np.array(
        [
            viewer.x_m + c * calibration.mount_x_m - s * calibration.mount_y_m,
            viewer.y_m + s * calibration.mount_x_m + c * calibration.mount_y_m,
            0.0,
        ]
    )
    yaw = viewer.theta_rad + math.radians(calibration.mount_yaw_deg)
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    return origin, right, down, forward


def project(
    calibration: CameraCalibration, viewer: Pose2D, points: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64] | None:
    """Pixel coordinates of world points (n x 3, z up), or None if any is behind the camera."""
    origin, right, down, forward = _camera_axes(calibration, viewer)
    rel = points - origin
    z = rel @ forward
    if np.any(z <= 0.05):
        return None
    u = calibration.fx_px * (rel @ right) / z + calibration.cx_px
    v = calibration.fy_px * (rel @ down) / z + calibration.cy_px
    return np.column_stack([u, v])


def render_view(
    calibration: CameraCalibration,
    viewer: Pose2D,
    target: Pose2D,
    *,
    card: Image,
    marker_size_m: float,
    face_deg: float = 180.0,
    depth_m: float = 0.0,
    noise_std: float = 0.0,
    seed: int = 0,
) -> Image:
    """What the camera on `viewer` sees of the card on `target` (a grey image)."""
    cv2 = _cv2()
    face = target.theta_rad + math.radians(face_deg)
    normal = np.array([math.cos(face), math.sin(face), 0.0])
    centre = np.array([target.x_m, target.y_m, 0.0]) + depth_m * normal
    up = np.array([0.0, 0.0, 1.0])
    across = np.cross(up, normal)  # the card's "right", seen from in front of it
    half = marker_size_m * (0.5 + CARD_MARGIN)
    corners = np.array(
        [centre + half * (sx * across + sy * up) for sx, sy in ((-1, 1), (1, 1), (1, -1), (-1, -1))]
    )
    image = np.full((calibration.height_px, calibration.width_px), BACKGROUND, dtype=np.uint8)
    pixels = project(calibration, viewer, corners)
    if pixels is not None:
        side = card.shape[0] - 1
        source = np.array([[0, 0], [side, 0], [side, side], [0, side]], dtype=np.float32)
        homography = cv2.getPerspectiveTransform(source, pixels.astype(np.float32))
        size = (calibration.width_px, calibration.height_px)
        warped = cv2.warpPerspective(card, homography, size, flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.full_like(card, 255), homography, size) > 127
        image[mask] = warped[mask]
    if noise_std > 0.0:
        noise = np.random.default_rng(seed).normal(0.0, noise_std, image.shape)
        image = np.clip(image + noise, 0, 255).astype(np.uint8)
    return image
