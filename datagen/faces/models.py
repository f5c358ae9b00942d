"""dlib and its face models, loaded once per process.

dlib comes from the ``dlib-bin`` wheel and is imported on first use. Its HOG detector is built in;
the MMOD CNN detector, the 5- and 68-point shape predictors and the face-recognition ResNet are read
from the ``face-recognition-models`` package.
"""
from __future__ import annotations

import functools
from importlib.util import find_spec
from pathlib import Path

from ..errors import NotInstalled, missing_extra, optional_import

FACES = "face detection (dlib)"


def load_dlib():
    """The dlib module; NotInstalled (an ImportError naming the 'faces' extra) without it."""
    return optional_import("dlib", "faces", FACES)


def models_dir() -> Path:
    """Folder of dlib's model files from the face-recognition-models package."""
    spec = find_spec("face_recognition_models")  # not imported: its __init__ needs pkg_resources
    if spec is None or not spec.submodule_search_locations:
        raise missing_extra("faces", FACES, "no module named 'face_recognition_models'")
    return Path(next(iter(spec.submodule_search_locations))) / "models"


def model_file(name: str) -> str:
    """Path of one of dlib's model files; ImportError when it is missing."""
    path = models_dir() / name
    if not path.is_file():
        raise NotInstalled(f"{path} is missing: pip install --force-reinstall face-recognition-models")
    return str(path)


def check_dlib() -> None:
    """Raise NotInstalled (an ImportError, one line with the pip command) unless dlib and its model files are
    installed."""
    load_dlib()
    for name in ("mmod_human_face_detector.dat", "shape_predictor_5_face_landmarks.dat",
                 "shape_predictor_68_face_landmarks.dat", "dlib_face_recognition_resnet_model_v1.dat"):
        model_file(name)


@functools.lru_cache(maxsize=None)
def hog_detector():
    """dlib's HOG frontal face detector (built in; one per process)."""
    return load_dlib().get_frontal_face_detector()


@functools.lru_cache(maxsize=None)
def cnn_detector():
    """dlib's MMOD CNN face detector (``mmod_human_face_detector.dat``; one per process). Its window
    finds faces of about 80 px and larger; detections have confidence above 0."""
    return load_dlib().cnn_face_detection_model_v1(model_file("mmod_human_face_detector.dat"))


@functools.lru_cache(maxsize=None)
def shape_predictor(points: int):
    """dlib's 5- or 68-point shape predictor (one per process)."""
    return load_dlib().shape_predictor(model_file(f"shape_predictor_{points}_face_landmarks.dat"))


@functools.lru_cache(maxsize=None)
def recognition_net():
    """dlib's face-recognition ResNet (one per process)."""
    return load_dlib().face_recognition_model_v1(model_file("dlib_face_recognition_resnet_model_v1.dat"))
