"""Relative sensing from a camera: fiducial markers (AprilTag 36h11 by default, through
OpenCV's `aruco` module, `opencv-contrib-python-headless`) on the other robots, read
into range, bearing and relative heading of each robot whose marker is seen.

`MarkerDetector` turns one image into `RelativeFix` values: it finds the markers, solves
each one's pose from its four corners with the camera's calibration (`solvePnP`,
IPPE_SQUARE: the planar square's two solutions told apart by reprojection), and puts it
in the robot's body frame through the camera's mount. The robot carrying a marker has
its centre `marker_depth_m` behind the marker's face, which looks `face_deg` from its
heading. `MarkerCamera` runs a detector on a live camera in a thread and hands the
measurements over with the time each frame was taken.

OpenCV's camera frame: x right, y down, z along the optical axis; a marker's own frame:
x right, y up, z out of its face. OpenCV is imported only when a detector is built.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.fixes import RelativeFix
from phalanx.core.lifecycle import Closing
from phalanx.core.localisation import CameraCalibration, MarkerSource

log = logging.getLogger("phalanx.markers")
# A second pose within this of the best one's reprojection error (ratio, px), facing
# more than this differently, makes the heading ambiguous: range and bearing only.
AMBIGUOUS_RATIO = 2.0
AMBIGUOUS_PX = 0.3
AMBIGUOUS_RAD = math.radians(3.0)
Image = npt.NDArray[np.uint8]


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - the extra is missing
        raise RuntimeError(
            "marker detection needs OpenCV: pip install 'phalanx[sensing]' "
            "(opencv-contrib-python-headless)"
        ) from exc
    return cv2


def camera_matrix(calibration: CameraCalibration) -> npt.NDArray[np.float64]:
    """The pinhole matrix K."""
    c = calibration
    return np.array([[c.fx_px, 0.0, c.cx_px], [0.0, c.fy_px, c.cy_px], [0.0, 0.0, 1.0]])


class MarkerDetector:
    """Markers in an image -> relative measurements of the robots carrying them."""

    def __init__(
        self,
        calibration: CameraCalibration,
        source: MarkerSource,
        *,
        robot_ids: tuple[str, ...],
        own_id: str,
    ) -> None:
        cv2 = _cv2()
        self.cv2, self.calibration, self.source, self.own_id = cv2, calibration, source, own_id
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, source.dictionary))
        parameters = cv2.aruco.DetectorParameters()
        parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self.detector = cv2.aruco.ArucoDetector(dictionary, parameters)
        self.owners = dict(enumerate(robot_ids)) | dict(source.marker_ids)
        self.k = camera_matrix(calibration)
        self.dist = np.array(calibration.distortion or (0.0, 0.0, 0.0, 0.0), dtype=np.float64)
        half = source.marker_size_m / 2
        # the marker's corners in its own frame, in aruco's order (top-left first, clockwise)
        self.corners = np.array(
            [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]
        )
        self.seen = 0
        self.unknown = 0
        self.ambiguous = 0  # seen, but its heading could be either of two

    def detect(self, image: Image, stamp_s: float) -> list[RelativeFix]:
        """The robots whose markers `image` shows, taken at `stamp_s` (fleet clock)."""
        gray = image if image.ndim == 2 else self.cv2.cvtColor(image, self.cv2.COLOR_BGR2GRAY)
        corners, ids, _rejected = self.detector.detectMarkers(gray)
        if ids is None:
            return []
        out = []
        for quad, marker_id in zip(corners, ids.ravel().tolist(), strict=True):
            owner = self.owners.get(int(marker_id))
            if owner is None or owner == self.own_id:
                self.unknown += 1
                continue
            fix = self._measure(quad.reshape(4, 2), int(marker_id), owner, stamp_s)
            if fix is not None:
                self.seen += 1
                out.append(fix)
        return out

    def _poses(self, quad: npt.NDArray[np.float64]) -> list[tuple[float, Any, Any]]:
        """Candidate poses of one marker, best first: (reprojection error px, rvec, tvec).

        A planar square seen nearly face-on has two poses that project almost alike (its
        tilt one way or the other): IPPE gives both; the iterative solver's answer joins
        them (IPPE alone misses the exactly face-on case in some builds).
        """
        cv2, out = self.cv2, []
        for flag in (cv2.SOLVEPNP_IPPE_SQUARE, cv2.SOLVEPNP_ITERATIVE):
            count, rvecs, tvecs, _errors = cv2.solvePnPGeneric(
                self.corners, quad, self.k, self.dist, flags=flag
            )
            for rvec, tvec in zip(rvecs[:count], tvecs[:count], strict=True):
                projected, _ = cv2.projectPoints(self.corners, rvec, tvec, self.k, self.dist)
                error = float(np.sqrt(np.mean(np.sum((projected.reshape(4, 2) - quad) ** 2, 1))))
                out.append((error, rvec, tvec))
        return sorted(out, key=lambda c: c[0])

    def _measure(
        self, quad: npt.NDArray[np.float32], marker_id: int, owner: str, stamp_s: float
    ) -> RelativeFix | None:
        candidates = self._poses(quad.astype(np.float64))
        if not candidates:
            return None
        best_error, rvec, tvec = candidates[0]
        face = self._face(rvec)
        # heading only if no pose that projects about as well faces another way
        ambiguous = any(
            error < AMBIGUOUS_RATIO * best_error + AMBIGUOUS_PX
            and abs(_wrap(self._face(other) - face)) > AMBIGUOUS_RAD
            for error, other, _ in candidates[1:]
        )
        t = tvec.ravel()
        cam = self.calibration
        yaw = math.radians(cam.mount_yaw_deg)
        depth = self.source.marker_depth_m
        forward, left = t[2], -t[0]
        mx = cam.mount_x_m + forward * math.cos(yaw) - left * math.sin(yaw)
        my = cam.mount_y_m + forward * math.sin(yaw) + left * math.cos(yaw)
        cx, cy = mx - depth * math.cos(face), my - depth * math.sin(face)
        face_deg = self.source.face_deg.get(marker_id, 180.0)
        rng = math.hypot(cx, cy)
        src = self.source
        if ambiguous:
            self.ambiguous += 1
        return RelativeFix(
            stamp_s=stamp_s,
            target_id=owner,
            range_m=rng,
            bearing_rad=math.atan2(cy, cx),
            std_range_m=max(src.range_std_frac * rng, 1e-3),
            std_bearing_rad=math.radians(src.bearing_std_deg),
            heading_rad=None if ambiguous else _wrap(face - math.radians(face_deg)),
            std_heading_rad=math.radians(src.heading_std_deg) * max(1.0, rng),
        )

    def _face(self, rvec: Any) -> float:
        """Where the marker's face looks, in the robot's body frame (rad)."""
        rot, _ = self.cv2.Rodrigues(rvec)
        normal = rot[:, 2]  # camera frame: x right, y down, z along the optical axis
        return _wrap(
            math.atan2(-normal[0], normal[2]) + math.radians(self.calibration.mount_yaw_deg)
        )


class MarkerCamera(Closing):
    """A live camera read in a thread: each frame's markers, stamped when it was taken
    (`clock()`: the fleet clock, `latency_s`: from exposure to the frame in memory).
    """

    def __init__(
        self,
        device: str | int,
        detector: MarkerDetector,
        *,
        clock: Callable[[], float],
        latency_s: float = 0.0,
    ) -> None:
        self.device, self.detector, self.clock, self.latency_s = device, detector, clock, latency_s
        self._lock = threading.Lock()
        self._pending: list[RelativeFix] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frames = 0

    def start(self) -> MarkerCamera:
        """Open the camera and read it in the background."""
        cv2 = _cv2()
        device = int(self.device) if str(self.device).isdigit() else self.device
        capture = cv2.VideoCapture(device)
        if not capture.isOpened():
            raise RuntimeError(f"camera {self.device!r}: could not open it")
        self._thread = threading.Thread(target=self._run, args=(capture,), daemon=True)
        self._thread.start()
        return self

    def _run(self, capture: Any) -> None:
        try:
            while not self._stop.is_set():
                ok, frame = capture.read()
                stamp = self.clock() - self.latency_s
                if not ok:
                    time.sleep(0.01)
                    continue
                self.frames += 1
                found = self.detector.detect(frame, stamp)
                with self._lock:
                    self._pending.extend(found)
                    del self._pending[:-200]
        finally:
            capture.release()

    def drain(self) -> tuple[RelativeFix, ...]:
        """Every measurement since the last call."""
        with self._lock:
            out, self._pending = tuple(self._pending), []
        return out

    def close(self) -> None:
        """Stop reading and release the camera (safe twice)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi
