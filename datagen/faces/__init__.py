"""Faces in photos and renders, offline, with dlib: detection and landmarks (:mod:`.detect`), head
crops (:mod:`.crop`), identity similarity, CSIM (:mod:`.identity`) and head pose, APD (:mod:`.pose`).

Needs ``dlib`` (the ``dlib-bin`` wheel) and the model files of ``face-recognition-models``
(:mod:`.models`). Images are numpy arrays (H, W, 3) RGB, uint8 or float in [0, 1]; points and boxes
are in pixels of the image they came from, (x, y), pixel (row i, column j) centred at (j, i).
"""
from .crop import CENTRE_BELOW_EYES, CROP_SIDE, EYE_DISTANCE, EYE_TO_MOUTH, crop_head, head_quad, warp_quad
from .detect import Box, detect_faces, landmarks
from .identity import FaceEmbedder, csim, csim_between_subjects
from .images import FaceError, to_float_rgb
from .models import check_dlib, cnn_detector, hog_detector, model_file
from .pose import GENERIC_FACE, HeadPose, apd, head_pose, pose_from_landmarks

__all__ = ["Box", "CENTRE_BELOW_EYES", "CROP_SIDE", "EYE_DISTANCE", "EYE_TO_MOUTH", "FaceEmbedder",
           "FaceError", "GENERIC_FACE", "HeadPose", "apd", "check_dlib", "cnn_detector", "crop_head", "csim",
           "csim_between_subjects", "detect_faces", "head_pose", "head_quad", "hog_detector", "landmarks",
           "model_file", "pose_from_landmarks", "to_float_rgb", "warp_quad"]
