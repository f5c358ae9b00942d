"""Face detection, EG3D-framed head crops, CSIM and head pose on scikit-image's bundled astronaut
portrait (a real photo) and its variants; head-pose geometry on synthetic projections."""
import io
import math

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from datagen.shards import to_uint8
from panolam import faces
from panolam.faces import (CENTRE_BELOW_EYES, CROP_SIDE, EYE_DISTANCE, EYE_TO_MOUTH, GENERIC_FACE,
                           FaceError, apd, crop_head, csim, detect_faces, head_pose, landmarks, load_image,
                           pose_from_landmarks, prepare_photo)

try:
    faces.check_dlib()
    HAVE_DLIB = True
except ImportError:
    HAVE_DLIB = False
needs_dlib = pytest.mark.skipif(not HAVE_DLIB, reason="needs dlib (pip install dlib-bin) and face-recognition-models")
OUT = 256


@pytest.fixture(scope="module")
def photo():
    data = pytest.importorskip("skimage.data", reason="scikit-image ships the astronaut portrait")
    return data.astronaut()


def encode(array, fmt, **kw):
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, fmt, **kw)
    return buf.getvalue()


def eye_mouth(lm):
    """Eye midpoint, eye-to-eye and eye-to-mouth vectors of 68 landmarks."""
    eye_l, eye_r = lm[36:42].mean(0), lm[42:48].mean(0)
    mid = (eye_l + eye_r) / 2
    return mid, eye_r - eye_l, (lm[48] + lm[54]) / 2 - mid


@needs_dlib
def test_detects_the_astronaut_once(photo):
    boxes = detect_faces(photo)
    assert len(boxes) == 1 and boxes == detect_faces(photo)
    box = boxes[0]
    mid, _, _ = eye_mouth(landmarks(photo, box))
    assert box.left < mid[0] < box.right and box.top < mid[1] < box.bottom and 60 < box.width < 130
    # HOG alone also fires on the mission patch on her suit; the CNN confirmation drops it
    assert len(detect_faces(photo, verify=False)) == 2


@needs_dlib
def test_crop_is_square_deterministic_and_eg3d_framed(photo):
    crop, info = prepare_photo(photo, OUT)
    again, _ = prepare_photo(photo, OUT)
    assert crop.shape == (OUT, OUT, 3) and crop.dtype == np.float32 and np.array_equal(crop, again)
    assert 0 <= crop.min() and crop.max() <= 1 and info["n_faces"] == 1 and info["upsampled"]
    assert np.array_equal(crop, crop_head(photo, info["box"], OUT))
    # landmarks found again in the crop: centre and size as head_quad builds them (to a few px)
    mid, e2e, e2m = eye_mouth(landmarks(to_uint8(crop), detect_faces(crop)[0]))
    centre = mid + CENTRE_BELOW_EYES * e2m
    assert np.allclose(centre, OUT / 2, atol=0.03 * OUT)
    size = CROP_SIDE * max(np.hypot(*e2e) / EYE_DISTANCE, np.hypot(*e2m) / EYE_TO_MOUTH)
    assert abs(size / OUT - 1) < 0.05
    assert 0.24 < np.hypot(*e2e) / OUT < 0.29 and 0.33 < mid[1] / OUT < 0.45  # EG3D: 0.266, 0.376
    wider, _ = prepare_photo(photo, OUT, scale=1.5)
    assert np.hypot(*eye_mouth(landmarks(to_uint8(wider), detect_faces(wider)[0]))[1]) < 0.75 * np.hypot(*e2e)


@pytest.fixture(scope="module")
def base_crop(photo):
    return prepare_photo(photo, OUT)


@needs_dlib
@pytest.mark.parametrize("variant", ["flip", "rotate 10", "rotate 25", "gray", "rgba", "uint16", "png16 gray",
                                     "jpeg file", "huge 4x", "face at the border", "32 px face"])
def test_photo_variants_work(photo, base_crop, variant, tmp_path):
    base, base_info = base_crop
    pil = Image.fromarray(photo)
    src = {
        "flip": photo[:, ::-1],
        "rotate 10": np.asarray(pil.rotate(10, resample=Image.BILINEAR)),
        "rotate 25": np.asarray(pil.rotate(25, resample=Image.BILINEAR)),
        "gray": np.asarray(pil.convert("L")),
        "rgba": np.dstack([photo, np.full(photo.shape[:2], 255, np.uint8)]),
        "uint16": photo.astype(np.uint16) * 257,
        "png16 gray": encode(np.asarray(pil.convert("L")).astype(np.uint16) * 257, "PNG"),
        "jpeg file": tmp_path / "astronaut.jpg",
        "huge 4x": np.asarray(pil.resize((2048, 2048), Image.BICUBIC)),
        "face at the border": photo[60:, 150:],
        "32 px face": np.asarray(pil.crop((130, 30, 310, 210)).resize((32, 32), Image.LANCZOS)),
    }[variant]
    (tmp_path / "astronaut.jpg").write_bytes(encode(photo, "JPEG", quality=95))
    crop, info = prepare_photo(src, OUT)
    assert crop.shape == (OUT, OUT, 3) and info["n_faces"] == 1 and np.isfinite(crop).all()
    if variant == "flip":
        assert np.abs(crop - base[:, ::-1]).mean() < 0.03
    elif variant == "huge 4x":
        assert abs(info["face_px"] / base_info["face_px"] - 4) < 0.2 and not info["upsampled"]
        assert np.abs(crop - base).mean() < 0.03
    elif variant in ("rgba", "uint16", "jpeg file", "face at the border"):
        assert np.abs(crop - base).mean() < 0.03


@needs_dlib
def test_photo_failures_are_one_line_face_errors(photo, tmp_path):
    pil = Image.fromarray(photo)
    cases = {
        "no face": [np.asarray(pil.rotate(90)), np.full((256, 256, 3), 200, np.uint8),
                    np.asarray(pil.resize((32, 32), Image.LANCZOS))],
        "cannot read image": [tmp_path / "cut.jpg", b"not an image", tmp_path / "missing.png"],
    }
    (tmp_path / "cut.jpg").write_bytes(encode(photo, "JPEG")[:5000])
    for message, sources in cases.items():
        for src in sources:
            with pytest.raises(FaceError, match=message) as err:
                prepare_photo(src, OUT)
            assert "\n" not in str(err.value)
    with pytest.raises(FaceError, match="truncated"):
        prepare_photo(tmp_path / "cut.jpg", OUT)
    with pytest.raises(FaceError, match="32x32 px"):
        prepare_photo(np.asarray(pil.resize((32, 32), Image.LANCZOS)), OUT)


@needs_dlib
def test_two_faces_need_pick_largest(photo):
    pair = np.concatenate([photo, photo], axis=1)
    with pytest.raises(FaceError, match="2 faces found.*pick='largest'"):
        prepare_photo(pair, OUT)
    crop, info = prepare_photo(pair, OUT, pick="largest")
    assert info["n_faces"] == 2 and crop.shape == (OUT, OUT, 3)


def test_load_image_alpha_and_16_bit():
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., 3] = 255
    rgba[0, 0, 3] = 0  # transparent black -> white
    img, _ = load_image(encode(rgba, "PNG"))
    assert img.shape == (4, 4, 3) and np.all(img[0, 0] == 1) and np.all(img[1, 1] == 0)
    gray16 = np.full((4, 4), 1000, np.uint16)
    img, _ = load_image(encode(gray16, "PNG"))
    assert np.allclose(img, 1000 / 65535)
    with pytest.raises(FaceError, match="shape"):
        load_image(np.zeros((2, 2, 2, 2)))


@needs_dlib
def test_csim(photo):
    data = pytest.importorskip("skimage.data")
    assert abs(csim(photo, photo) - 1) < 1e-6
    crop, _ = prepare_photo(photo[:, 40:], 384)  # cropped, resampled and shifted
    assert 0.9 < csim(photo, crop) < 1
    assert math.isnan(csim(photo, data.chelsea()))  # a cat: no face


@needs_dlib
def test_csim_of_a_render_the_detector_misses_uses_the_targets_face_box(photo):
    from scipy import ndimage
    data = pytest.importorskip("skimage.data")
    blur = lambda sigma: ndimage.gaussian_filter(photo.astype(np.float32), (sigma, sigma, 0)).astype(np.uint8)  # noqa: E731
    assert not detect_faces(blur(8)) and math.isnan(csim(blur(8), photo))
    soft, softer = csim(blur(5), photo, box_from_b=True), csim(blur(12), photo, box_from_b=True)
    assert 0.5 < softer < soft < 1
    assert math.isnan(csim(photo, data.chelsea(), box_from_b=True))  # no face in the target


def project(yaw, pitch, roll, size=512, fov=faces.TRAINING_FOV_DEG, distance=700.0):
    """68-point array holding GENERIC_FACE seen at these angles (other points left at zero)."""
    rot = Rotation.from_euler("YXZ", [-yaw, -pitch, roll], degrees=True)
    f = 0.5 * size / math.tan(math.radians(fov) / 2)
    lm = np.zeros((68, 2))
    for i, p in GENERIC_FACE.items():
        cam = rot.apply(p) + [10.0, -5.0, distance]
        lm[i] = cam[:2] / cam[2] * f + size / 2
    return lm


@pytest.mark.parametrize("angles", [(0, 0, 0), (30, -10, 5), (-40, 15, -20), (10, 25, 0)])
def test_pose_from_landmarks_recovers_angles(angles):
    assert np.allclose(pose_from_landmarks(project(*angles), 512, 512), angles, atol=0.05)


def test_pose_signs():
    lm = project(20, 0, 0)
    assert lm[30, 0] > (lm[36, 0] + lm[45, 0]) / 2  # yaw > 0: the nose points to the image right
    assert project(0, 20, 0)[30, 1] < project(0, 0, 0)[30, 1]  # pitch > 0: looks up
    lm = project(0, 0, 20)
    assert lm[45, 1] > lm[36, 1]  # roll > 0: clockwise in the image


@needs_dlib
def test_head_pose_and_apd(photo):
    yaw, pitch, roll = head_pose(photo)
    assert abs(yaw) < 10 and abs(roll) < 10 and abs(pitch) < 25
    yaw_f, pitch_f, roll_f = head_pose(photo[:, ::-1])
    assert abs(yaw + yaw_f) < 3 and abs(roll + roll_f) < 3 and abs(pitch - pitch_f) < 3
    assert apd(photo, photo) == 0
    assert 0 < apd(photo, photo[:, ::-1]) < 5
    blank = np.full((128, 128, 3), 0.5, np.float32)
    assert math.isnan(apd(photo, blank))
    with pytest.raises(FaceError, match="no face"):
        head_pose(blank)


@needs_dlib
def test_csim_between_subjects_averages_pairs_of_found_faces(photo):
    from scipy import ndimage
    data = pytest.importorskip("skimage.data")
    sim, n = faces.csim_between_subjects([photo, photo, data.chelsea()])
    assert n == 2 and abs(sim - 1) < 1e-6
    soft = ndimage.gaussian_filter(photo.astype(np.float32), (3, 3, 0)).astype(np.uint8)
    sim, n = faces.csim_between_subjects([photo, soft])
    assert n == 2 and abs(sim - csim(photo, soft)) < 1e-6 and sim < 1
    sim, n = faces.csim_between_subjects([photo, data.chelsea()])
    assert n == 1 and math.isnan(sim)
