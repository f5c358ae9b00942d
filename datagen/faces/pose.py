"""Head pose (yaw, pitch, roll) from dlib's 68 landmarks, and the average pose distance (APD)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from datagen.cameras import FOV_MEAN, angle_between, fov_to_focal, intrinsics, pixel_intrinsics

from .detect import detect_faces, landmarks
from .images import FaceError, rgb_u8

DEFAULT_FOCAL = float(fov_to_focal(FOV_MEAN))  # normalized focal of the datasets' mean camera

# Generic adult face, mm: x toward the image right of a frontal face, y down, z away from the
# camera (OpenCV camera axes for a frontal pose); keys are dlib 68-point indices. Eye centres,
# nose tip and mouth corners follow the Deep3DFaceRecon mean face (see .crop; 0.1 unit = 10 mm); the
# other points are generic anthropometric estimates. Jaw contour, brows and lips (which slide or
# move with expression) are left out, except the chin.
GENERIC_FACE = {
    8: (0.0, 85.0, -15.0),                                   # chin
    27: (0.0, -31.0, -26.0),                                 # top of the nose bridge
    30: (0.0, 4.6, -55.2),                                   # nose tip
    31: (-14.0, 10.0, -36.0), 33: (0.0, 14.0, -40.0), 35: (14.0, 10.0, -36.0),  # nostrils
    36: (-45.0, -29.0, -6.0), 39: (-17.0, -29.0, -20.0),     # eye corners (outer, inner)
    42: (17.0, -29.0, -20.0), 45: (45.0, -29.0, -6.0),
    48: (-25.0, 38.1, -22.3), 54: (25.0, 38.1, -22.3),       # mouth corners
}


@dataclass(frozen=True)
class HeadPose:
    """A face's pose in the camera: degrees; yaw > 0: the face turns toward the image right; pitch > 0:
    it looks up; roll > 0: it tilts clockwise in the image. Rotation = Ry(-yaw) Rx(-pitch) Rz(roll)
    in OpenCV camera axes (GENERIC_FACE's axes for a frontal face). translation_mm: GENERIC_FACE's
    origin in camera coordinates, mm."""

    yaw: float
    pitch: float
    roll: float
    translation_mm: tuple

    @property
    def angles(self) -> tuple[float, float, float]:
        return self.yaw, self.pitch, self.roll


def pose_from_landmarks(lm68: np.ndarray, width: int, height: int, focal: float = DEFAULT_FOCAL) -> HeadPose:
    """The head pose of 68 landmarks: OpenCV's perspective PnP of GENERIC_FACE (Levenberg-Marquardt
    on the reprojection error from a frontal start) through the camera of :mod:`datagen.cameras`:
    normalized focal ``focal`` (EG3D's convention, the one every render uses), principal point at
    the image centre."""
    lm68 = np.asarray(lm68, np.float64)
    model = np.array(list(GENERIC_FACE.values()), np.float64)
    obs = lm68[list(GENERIC_FACE)] + 0.5  # pixel centres at +0.5, as the cameras' K
    K = pixel_intrinsics(intrinsics(focal), width, height)
    # start frontal, at the distance where the outer eye corners are as far apart as observed: a
    # free start can land on the mirror solution (the face upside down, roll 180 deg)
    z0 = K[0, 0] * (GENERIC_FACE[45][0] - GENERIC_FACE[36][0]) / max(np.hypot(*(lm68[45] - lm68[36])), 1e-6)
    centre = obs.mean(axis=0)
    tvec = np.array([(centre[0] - K[0, 2]) / K[0, 0] * z0, (centre[1] - K[1, 2]) / K[1, 1] * z0, z0])
    found, rvec, tvec = cv2.solvePnP(model, obs, K, None, np.zeros(3), tvec, useExtrinsicGuess=True,
                                     flags=cv2.SOLVEPNP_ITERATIVE)
    if not found:
        raise FaceError(f"no head pose fits these landmarks ({width}x{height} px)")
    y_angle, x_angle, z_angle = Rotation.from_rotvec(rvec.ravel()).as_euler("YXZ", degrees=True)
    return HeadPose(-y_angle, -x_angle, z_angle, tuple(tvec.ravel()))


def head_pose(image, focal: float = DEFAULT_FOCAL) -> HeadPose:
    """The head pose of the largest face (see pose_from_landmarks); FaceError when there is none.
    Landmark PnP with a generic face, not the paper's 3DMM-based estimator."""
    u8 = rgb_u8(image)
    faces = detect_faces(u8)
    if not faces:
        raise FaceError(f"no face found ({u8.shape[1]}x{u8.shape[0]} px)")
    return pose_from_landmarks(landmarks(u8, faces[0]), u8.shape[1], u8.shape[0], focal)


def apd(img_a, img_b, focal: float = DEFAULT_FOCAL) -> float:
    """Average pose distance: mean |difference| of yaw, pitch and roll in degrees between the faces
    of two images seen with normalized focal ``focal``; nan when either has no face (the caller
    reports how many were skipped). Ours is landmark PnP with a generic face; the paper's APD uses
    3DMM (Deep3DFaceRecon) angles."""
    try:
        a, b = head_pose(img_a, focal).angles, head_pose(img_b, focal).angles
    except FaceError:
        return math.nan
    return float(np.mean(angle_between(a, b)))
