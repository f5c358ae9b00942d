"""Face detection, EG3D-framed head crops, CSIM and head pose on scikit-image's bundled astronaut
portrait (a real photo) and its variants; head-pose geometry on synthetic projections."""
import io
import math

import numpy as np
import pytest
from PIL import Image, UnidentifiedImageError
from scipy.spatial.transform import Rotation

from datagen import faces
from datagen.cameras import (FOV_MEAN, RADIUS_MEAN, camera_position, fov_to_focal, intrinsics, look_at,
                             pixel_intrinsics)
from datagen.faces import (CENTRE_BELOW_EYES, CROP_SIDE, EYE_DISTANCE, EYE_TO_MOUTH, GENERIC_FACE, FaceError, apd,
                           crop_head, csim, detect_faces, head_pose, landmarks, pose_from_landmarks)
from datagen.dataset.shards import to_uint8
from panolam.photos import load_image, prepare_photo, read_photo

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
    with pytest.raises(FaceError, match="2 faces found.*--pick largest"):
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


MM = 1e-3 / 4.5  # world units per mm of GENERIC_FACE: eye corners 90 mm apart -> 0.02 units, a head-sized face
FACE_TO_WORLD = np.diag([1.0, -1.0, -1.0])  # GENERIC_FACE axes (x right, y down, z away) of a face looking at +z


def seen_from(yaw_deg, pitch_deg, radius=RADIUS_MEAN, fov=FOV_MEAN, size=512, head_yaw=0.0, head_roll=0.0):
    """68-point array (GENERIC_FACE's points, the others zero) of a generic face at the origin, turned
    by head_yaw about the world's up axis and tilted by head_roll, seen by the datasets' camera at
    (yaw, pitch, radius) looking at it: datagen.cameras' look-at and EG3D intrinsics, dlib's pixel
    convention (centres at integers). Returns the landmarks and the face's rotation in the camera."""
    c2w = look_at(camera_position(yaw_deg, pitch_deg, radius))
    w2c = np.linalg.inv(c2w)
    K = pixel_intrinsics(intrinsics(fov_to_focal(fov)), size, size)
    turn = Rotation.from_euler("yz", [head_yaw, head_roll], degrees=True).as_matrix()
    face_to_world = turn @ FACE_TO_WORLD
    lm = np.zeros((68, 2))
    for i, p in GENERIC_FACE.items():
        cam = w2c[:3, :3] @ (face_to_world @ (np.asarray(p) * MM)) + w2c[:3, 3]
        uv = K @ cam
        lm[i] = uv[:2] / uv[2] - 0.5
    return lm, w2c[:3, :3] @ face_to_world


def euler_of(rotation) -> tuple[float, float, float]:
    """(yaw, pitch, roll) of a face rotation in camera axes, as HeadPose defines them."""
    y, x, z = Rotation.from_matrix(rotation).as_euler("YXZ", degrees=True)
    return -y, -x, z


@pytest.mark.parametrize("yaw, pitch, head_yaw, head_roll", [(0, 0, 0, 0), (25, 0, 0, 0), (-30, 12, 0, 0),
                                                             (10, -20, 15, 0), (0, 8, 0, 20), (35, 20, -10, -15)])
def test_head_pose_through_the_datasets_cameras(yaw, pitch, head_yaw, head_roll):
    """Landmarks projected by the datasets' own camera code (EG3D focal) give back the face's pose in
    that camera and its distance: a pinhole focal 0.5 W / tan(fov / 2) would put it sqrt(2) nearer."""
    lm, rotation = seen_from(yaw, pitch, head_yaw=head_yaw, head_roll=head_roll)
    pose = pose_from_landmarks(lm, 512, 512)
    np.testing.assert_allclose(pose.angles, euler_of(rotation), atol=0.01)
    assert np.linalg.norm(pose.translation_mm) * MM == pytest.approx(RADIUS_MEAN, rel=1e-4)
    # the camera of another FOV: the estimate needs that camera's focal
    lm, _ = seen_from(yaw, pitch, fov=14.0, head_yaw=head_yaw, head_roll=head_roll)
    pose = pose_from_landmarks(lm, 512, 512, focal=float(fov_to_focal(14.0)))
    assert np.linalg.norm(pose.translation_mm) * MM == pytest.approx(RADIUS_MEAN, rel=1e-4)


def test_pose_signs():
    lm, _ = seen_from(0, 0, head_yaw=20)  # the face turns toward world +x, the frontal camera's image right
    assert lm[30, 0] > (lm[36, 0] + lm[45, 0]) / 2 and pose_from_landmarks(lm, 512, 512).yaw > 19
    assert pose_from_landmarks(seen_from(-20, 0)[0], 512, 512).yaw > 19  # as a camera moving to -x sees it
    above, level = seen_from(0, 20)[0], seen_from(0, 0)[0]  # a camera above sees the face look down
    assert above[30, 1] - above[27, 1] > level[30, 1] - level[27, 1]
    assert pose_from_landmarks(above, 512, 512).pitch < -19
    lm, _ = seen_from(0, 0, head_roll=-20)
    assert lm[45, 1] > lm[36, 1] and pose_from_landmarks(lm, 512, 512).roll > 19  # clockwise in the image


@needs_dlib
@pytest.mark.slow
def test_head_pose_of_procedural_renders_at_known_camera_angles():
    """Renders of procedural heads by the datasets' cameras at known yaw and pitch. The generic face is
    not the procedural one, so the frontal view's estimate is subtracted; dlib's landmarks on these
    stylised faces saturate beyond ~25 deg, so the views stay within +-20 deg."""
    from datagen.cameras import ViewSet
    from datagen.generators import make_generator
    generator = make_generator("procedural")
    yaw, pitch = np.array([0.0, -20, 20, 0, 0]), np.array([0.0, 0, 0, -12, 12])
    views = ViewSet("test", yaw, pitch, np.full(5, RADIUS_MEAN), np.full(5, FOV_MEAN), (0.0, 0.0, 0.0))
    errors, pitch_signs = [], []
    for index in range(3):
        rendered = generator.render(generator.sample_subject(3, index), views, 224)
        poses = []
        for rgb in rendered.rgb:
            try:
                poses.append(head_pose(to_uint8(rgb)))
            except FaceError:
                poses.append(None)
        if poses[0] is None:
            continue
        for i in (1, 2):  # the camera's yaw turns the face the other way
            if poses[i] is not None:
                errors.append(abs((poses[i].yaw - poses[0].yaw) + yaw[i]))
        for i in (3, 4):
            if poses[i] is not None:
                pitch_signs.append(np.sign(poses[i].pitch - poses[0].pitch) == -np.sign(pitch[i]))
    assert len(errors) >= 3 and np.median(errors) < 4.0, errors
    assert len(pitch_signs) >= 2 and all(pitch_signs)


@needs_dlib
def test_head_pose_and_apd(photo):
    yaw, pitch, roll = head_pose(photo).angles
    assert abs(yaw) < 10 and abs(roll) < 10 and abs(pitch) < 25
    yaw_f, pitch_f, roll_f = head_pose(photo[:, ::-1]).angles
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


# -- photo size limits and formats ----------------------------------------------------------------------------
def _png_header(width: int, height: int) -> bytes:
    """The start of a PNG that claims width x height px (its pixel data is missing)."""
    import struct
    import zlib
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = lambda kind, data: (struct.pack(">I", len(data)) + kind + data +  # noqa: E731
                                struct.pack(">I", zlib.crc32(kind + data)))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", b"\0" * 64)


def test_a_photo_above_the_pixel_limit_is_refused_from_its_header(tmp_path):
    import time
    (tmp_path / "huge.png").write_bytes(_png_header(12000, 12000))
    t0 = time.perf_counter()
    for src in (tmp_path / "huge.png", _png_header(12000, 12000)):
        with pytest.raises(FaceError, match="12000x12000 px is 144 megapixels, above the limit of 100"):
            read_photo(src)
    assert time.perf_counter() - t0 < 1  # nothing was decoded
    with pytest.raises(FaceError, match="cannot read image"):  # within the limit: decoding finds the data missing
        read_photo(_png_header(4000, 3000))


def test_a_large_photo_is_downscaled_as_it_is_decoded(photo, tmp_path):
    import tracemalloc
    big = Image.fromarray(photo).resize((6000, 4500), Image.BILINEAR)
    big.save(tmp_path / "big.jpg", quality=90)
    big.save(tmp_path / "big.png", compress_level=1)
    del big
    tracemalloc.start()
    jpeg = read_photo(tmp_path / "big.jpg")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    # the JPEG decoder itself works at half size (3000 px, under the 4096 px working limit), so no
    # full-size array ever exists: a float copy of the whole photo would take 324 MB
    assert jpeg.rgb.shape == (2250, 3000, 3) and jpeg.size == (6000, 4500) and jpeg.scale == 0.5
    assert peak < 0.5 * 6000 * 4500 * 3 * 4
    png = read_photo(tmp_path / "big.png")  # decoded whole (8 bits), then area-averaged
    assert png.rgb.shape[:2] == (3072, 4096) and png.scale == pytest.approx(4096 / 6000)
    small = np.asarray(Image.fromarray(to_uint8(png.rgb)).resize((512, 512), Image.BOX)).astype(float)
    assert np.abs(small - photo).mean() < 4  # the same picture


def test_formats_pillow_lacks_are_read_by_openimageio(photo, tmp_path):
    oiio = pytest.importorskip("OpenImageIO")
    srgb = photo.astype(np.float32) / 255
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4).astype(np.float32)
    out = oiio.ImageOutput.create(str(tmp_path / "photo.exr"))
    out.open(str(tmp_path / "photo.exr"), oiio.ImageSpec(512, 512, 3, "half"))
    out.write_image(linear)
    out.close()
    with pytest.raises(UnidentifiedImageError):
        Image.open(tmp_path / "photo.exr")
    back = read_photo(tmp_path / "photo.exr")
    assert back.rgb.shape == (512, 512, 3) and np.abs(back.rgb - srgb).max() < 2 / 255  # sRGB again
    with pytest.raises(FaceError, match="not an image format Pillow can decode"):  # bytes: Pillow only
        read_photo((tmp_path / "photo.exr").read_bytes())
    (tmp_path / "junk.exr").write_bytes(b"not an image at all")
    with pytest.raises(FaceError, match="not an image format Pillow or OpenImageIO can decode"):
        read_photo(tmp_path / "junk.exr")
    wide = np.tile(np.linspace(0, 1, 9000, dtype=np.float32), (6, 1))[..., None]  # 9000 px: read in strips, 1/3
    out = oiio.ImageOutput.create(str(tmp_path / "wide.exr"))
    out.open(str(tmp_path / "wide.exr"), oiio.ImageSpec(9000, 6, 1, "float"))
    out.write_image(wide)
    out.close()
    back = read_photo(tmp_path / "wide.exr")
    assert back.rgb.shape == (2, 3000, 3) and back.size == (9000, 6)
    expected = wide[:3, :, 0].reshape(3, 3000, 3).mean(axis=(0, 2))
    expected = np.where(expected <= 0.0031308, 12.92 * expected, 1.055 * expected ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(back.rgb[0, :, 0], expected, atol=1e-5)
