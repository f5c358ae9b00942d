"""Face identity: dlib ResNet embeddings and their cosine similarity (CSIM)."""
from __future__ import annotations

import functools
import math

import numpy as np

from .detect import Box, detect_faces, dlib_rect
from .images import rgb_u8
from .models import recognition_net, shape_predictor


class FaceEmbedder:
    """dlib's face-recognition ResNet (128-d, 5-point aligned 150 px chips) on the largest face.

    This is dlib's network, NOT the ArcFace (insightface) network the paper's CSIM uses: values
    are comparable between our own runs only, not with published CSIM numbers.
    """

    def embed(self, image, box: Box | None = None) -> np.ndarray | None:
        """128-d descriptor of the face in ``box`` (default: the largest face found), or None when no face is found."""
        u8 = rgb_u8(image)
        if box is None:
            faces = detect_faces(u8)
            if not faces:
                return None
            box = faces[0]
        shape = shape_predictor(5)(u8, dlib_rect(box))
        return np.asarray(recognition_net().compute_face_descriptor(u8, shape), dtype=np.float64)


@functools.lru_cache(maxsize=None)
def _embedder() -> FaceEmbedder:
    return FaceEmbedder()


def csim(img_a, img_b, embedder: FaceEmbedder | None = None, box_from_b: bool = False) -> float:
    """Identity similarity: cosine of dlib ResNet embeddings (not ArcFace, see FaceEmbedder), in
    [-1, 1]; nan when either image has no face (the caller counts and reports those skipped).

    ``box_from_b``: the face box found in ``img_b`` locates the face in ``img_a`` too (landmarks
    are still fitted in each image), for a render and its target seen from the same camera: a
    blurry render the detector misses is still compared where the target's face is."""
    embedder = embedder or _embedder()
    if box_from_b:
        faces = detect_faces(img_b)
        if not faces:
            return math.nan
        a, b = embedder.embed(img_a, faces[0]), embedder.embed(img_b, faces[0])
    else:
        a, b = embedder.embed(img_a), embedder.embed(img_b)
    if a is None or b is None:
        return math.nan
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def csim_between_subjects(images, embedder: FaceEmbedder | None = None) -> tuple[float, int]:
    """Mean CSIM over all pairs of different images, each at its own largest face, and how many
    faces were found; (nan, n) with fewer than two. Over targets of different subjects this is
    what an identity-blind prediction scores: a reconstruction shows identity only above it."""
    embedder = embedder or _embedder()
    found = [e / np.linalg.norm(e) for e in map(embedder.embed, images) if e is not None]
    if len(found) < 2:
        return math.nan, len(found)
    sim = np.stack(found) @ np.stack(found).T
    return float(sim[~np.eye(len(found), dtype=bool)].mean()), len(found)

