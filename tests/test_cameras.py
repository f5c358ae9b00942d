import math

import numpy as np
import pytest
import torch

from datagen import cameras as C
from tests.conftest import gan_fixture


def test_eg3d_focal_fov_values():
    assert C.fov_to_focal(18.837) == pytest.approx(4.2634, abs=2e-4)
    # EG3D's scripts hard-code 4.2647 for "18.837 deg": the 1.414 convention is within 0.05 %.
    assert C.fov_to_focal(18.837) == pytest.approx(C.EG3D_FOCAL, rel=5e-4)
    assert C.focal_to_fov(C.EG3D_FOCAL) == pytest.approx(18.83, abs=0.01)
    assert C.horizontal_fov(C.EG3D_FOCAL) == pytest.approx(13.38, abs=0.01)


def test_fov_focal_round_trip():
    fov = np.random.default_rng(0).uniform(5, 60, 100)
    np.testing.assert_allclose(C.focal_to_fov(C.fov_to_focal(fov)), fov, rtol=1e-12)


def test_frontal_pose_matches_eg3d_conditioning():
    c2w = C.eg3d_lookat_pose(math.pi / 2, math.pi / 2, 2.7, C.EG3D_PIVOT)
    expected = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 2.7], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(c2w, expected, atol=1e-12)
    c = C.conditioning_vector(c2w, C.intrinsics(C.EG3D_FOCAL))
    assert c.shape == (25,)
    np.testing.assert_allclose(c[16:], [4.2647, 0, 0.5, 0, 4.2647, 0.5, 0, 0, 1])
    # Our yaw/pitch parameterisation gives the same frontal camera.
    np.testing.assert_allclose(C.look_at(C.camera_position(0, 0, 2.7), C.EG3D_PIVOT), expected, atol=1e-12)


@pytest.mark.parametrize("model", ["eg3d", "panohead"])
def test_poses_match_the_official_camera_sampler(model):
    """The fixture's cameras were made by the original LookAtPoseSampler."""
    z = np.load(gan_fixture(model, "-fixture.npz"))
    for (yaw_deg, pitch_rad), c in zip(z["cam_yaw_pitch"], z["cams"]):
        c2w = C.eg3d_lookat_pose(math.pi / 2 + math.radians(yaw_deg), math.pi / 2 + pitch_rad, 2.7,
                                 tuple(z["cam_pivot"]))
        ours = C.conditioning_vector(c2w, C.intrinsics(C.EG3D_FOCAL))
        np.testing.assert_allclose(ours, c, atol=2e-6)
        if pitch_rad == 0:  # EG3D's v is not an angle; at pitch 0 our yaw convention must agree
            pos = C.camera_position(yaw_deg, 0.0, 2.7)
            np.testing.assert_allclose(C.look_at(pos, tuple(z["cam_pivot"])), c2w, atol=1e-9)


@pytest.mark.parametrize("pitch", [90.0, -90.0, 89.9999, -89.9999])
def test_poles_are_finite_and_orthonormal(pitch):
    c2w = C.look_at(C.camera_position(30.0, pitch, 2.7), (0, 0, 0))
    R = c2w[:3, :3]
    assert np.isfinite(c2w).all()
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    forward = -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
    np.testing.assert_allclose(R[:, 2], forward, atol=1e-9)


def test_pole_orientation_is_continuous():
    exact = C.look_at(C.camera_position(0.0, 90.0, 2.7))
    near = C.look_at(C.camera_position(0.0, 89.99, 2.7))
    np.testing.assert_allclose(exact[:3, :3], near[:3, :3], atol=1e-3)
    exact = C.look_at(C.camera_position(0.0, -90.0, 2.7))
    near = C.look_at(C.camera_position(0.0, -89.99, 2.7))
    np.testing.assert_allclose(exact[:3, :3], near[:3, :3], atol=1e-3)


def test_ray_range_moves_with_radius():
    assert C.ray_range(2.7) == pytest.approx((2.25, 3.3))
    near, far = C.ray_range(np.array([2.4, 3.0]))
    np.testing.assert_allclose(near, [1.95, 2.55])
    np.testing.assert_allclose(far, [3.0, 3.6])


def test_rays_centre_and_corner():
    c2w = C.look_at(C.camera_position(40.0, 10.0, 2.7), (0, 0, 0))
    K = C.intrinsics(C.EG3D_FOCAL)
    origins, dirs = C.rays(torch.tensor(c2w[None]), torch.tensor(K[None]), 3)
    np.testing.assert_allclose(dirs[0, 4].numpy(), c2w[:3, 2], atol=1e-6)  # middle pixel looks forward
    np.testing.assert_allclose(origins[0, 0].numpy(), c2w[:3, 3], atol=1e-6)
    np.testing.assert_allclose(dirs.norm(dim=-1).numpy(), 1.0, atol=1e-6)
    # Top-left pixel centre: u = v = 1/6, so the ray is atan((1/6 - 1/2) / f) off-axis on both axes.
    d_cam = c2w[:3, :3].T @ dirs[0, 0].numpy().astype(float)
    assert d_cam[0] / d_cam[2] == pytest.approx(-1 / 3 / C.EG3D_FOCAL, rel=1e-5)
    assert d_cam[1] / d_cam[2] == pytest.approx(-1 / 3 / C.EG3D_FOCAL, rel=1e-5)


def test_pixel_intrinsics():
    K = C.pixel_intrinsics(C.intrinsics(4.0), 512, 512)
    np.testing.assert_allclose(K, [[2048, 0, 256], [0, 2048, 256], [0, 0, 1]])


def test_frontal_protocol_statistics():
    rng = np.random.default_rng(1)
    draws = [C.sample_views("frontal", rng) for _ in range(300)]
    yaw = np.concatenate([d.yaw for d in draws])
    pitch = np.concatenate([d.pitch for d in draws])
    radius = np.concatenate([d.radius for d in draws])
    fov = np.concatenate([d.fov for d in draws])
    assert len(draws[0]) == 32 and draws[0].pivot == C.EG3D_PIVOT
    assert yaw.min() >= -36 and yaw.max() <= 36 and yaw.max() - yaw.min() > 70
    assert pitch.min() >= -26 and pitch.max() <= 26 and pitch.max() - pitch.min() > 50
    assert radius.mean() == pytest.approx(2.7, abs=0.01) and radius.std() == pytest.approx(0.1, abs=0.01)
    assert fov.mean() == pytest.approx(18.83, abs=0.05) and fov.std() == pytest.approx(1.0, abs=0.05)
    assert abs(yaw.mean()) < 1.0 and abs(pitch.mean()) < 1.0


def test_360_protocol_statistics():
    rng = np.random.default_rng(2)
    draws = [C.sample_views("360", rng) for _ in range(300)]
    for d in draws[:5]:
        np.testing.assert_allclose(d.yaw[:8], np.arange(8) * 45.0)
        np.testing.assert_allclose(d.pitch[:8], 0.0)
    yaw = np.concatenate([d.yaw[8:] for d in draws])
    assert yaw.min() >= 0 and yaw.max() < 360
    quadrant_share = np.bincount((yaw // 90).astype(int), minlength=4) / len(yaw)
    np.testing.assert_allclose(quadrant_share, 0.25, atol=0.02)
    pitch = np.concatenate([d.pitch[8:] for d in draws])
    assert np.abs(pitch).max() <= 26
    assert draws[0].pivot == C.HEAD360_PIVOT


def test_protocol_is_reproducible_and_clipped():
    a = C.sample_views("360", np.random.default_rng(5))
    b = C.sample_views("360", np.random.default_rng(5))
    np.testing.assert_array_equal(a.cam2world, b.cam2world)
    rng = np.random.default_rng(3)
    radius = np.concatenate([C.sample_views("frontal", rng).radius for _ in range(2000)])
    assert radius.min() >= 2.7 - 0.4 and radius.max() <= 2.7 + 0.4


def test_unknown_protocol():
    with pytest.raises(ValueError, match="unknown protocol"):
        C.sample_views("sideways", np.random.default_rng(0))


def test_viewset_records_round_trip():
    v = C.sample_views("frontal", np.random.default_rng(4), 5)
    back = C.ViewSet.from_records(v.to_records(), v.protocol, v.pivot)
    np.testing.assert_allclose(back.cam2world, v.cam2world)
    np.testing.assert_allclose(back.K, v.K)
