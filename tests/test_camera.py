"""Camera geometry and detector noise against independent computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.scenario import load_scenario
from bench.sim.world_builder import build_terrain, build_world
from models.camera import CameraConfig, apply_detector_noise, detector_normal, intrinsics
from tests.conftest import SMALL_SET


def test_intrinsics_from_fov_and_resolution():
    cfg = CameraConfig(width_px=320, height_px=240, fovy_deg=50.0)
    K = intrinsics(cfg)
    # A ray at the top edge of the vertical FOV lands half a pixel outside the first row centre.
    top_ray = np.array([0.0, -math.tan(math.radians(25.0)), 1.0])
    uv = K @ top_ray
    assert abs(uv[1] / uv[2] - (-0.5)) < 1e-9
    assert K[0, 0] == K[1, 1] and K[0, 2] == 159.5 and K[1, 2] == 119.5


@pytest.fixture(scope="module")
def posed_world():
    scenario = load_scenario(None, SMALL_SET + ["camera.width_px=160", "camera.height_px=120", "camera.fovy_deg=45"])
    terrain = build_terrain(scenario)
    world = build_world(scenario, terrain)
    q = Rotation.from_euler("xyz", [6.0, -4.0, 25.0], degrees=True).as_quat(scalar_first=True)
    world.reset(np.array([7.0, -4.0, 90.0]), np.zeros(3), q, np.zeros(3))
    yield world, terrain
    world.close()


def test_terrain_point_projects_through_K_to_where_depth_puts_it(posed_world):
    world, terrain = posed_world
    K, (R_LC, r_CL_L) = world.K, world.camera_pose()
    depth = world.render_depth().astype(np.float64)
    H, W = depth.shape
    # Back-project every pixel through the rendered depth into L.
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays_C = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
    pts_L = (R_LC @ (rays_C * depth.ravel())).T + r_CL_L
    n = terrain.height_m.shape[0]
    spacing = terrain.spacing_m
    checked = 0
    for row in range(0, n, 2):
        for col in range(0, n, 2):
            p_L = np.array([-terrain.size_m / 2 + col * spacing, -terrain.size_m / 2 + row * spacing, terrain.height_m[row, col]])
            p_C = R_LC.T @ (p_L - r_CL_L)
            uv = (K @ p_C)[:2] / p_C[2]
            if not (5 <= uv[0] <= W - 6 and 5 <= uv[1] <= H - 6):
                continue
            dist = np.linalg.norm(pts_L - p_L, axis=1)
            k = int(np.argmin(dist))
            found = np.array([k % W, k // W], float)
            assert np.linalg.norm(found - uv) <= 1.0, (row, col, uv, found)
            # The depth image is metric z-depth: the nearest back-projected point is within a pixel footprint.
            assert dist[k] < 1.5 * p_C[2] / K[0, 0] + 0.05
            assert abs(depth[int(round(uv[1])), int(round(uv[0]))] - p_C[2]) < 0.02 * p_C[2]
            checked += 1
    assert checked >= 4, "too few terrain vertices in view to test"


def test_detector_noise_statistics():
    cfg = CameraConfig(read_noise_dn=2.0, gain_e_per_dn=10.0)
    signal = np.full((300, 300), 100, np.uint8)
    img = apply_detector_noise(signal, cfg, np.random.default_rng(0)).astype(float)
    # Variance in DN^2 = shot (S / g) + read^2 + quantisation (1/12).
    expected_var = 100 / 10.0 + 2.0**2 + 1 / 12
    assert abs(img.mean() - 100) < 0.1
    assert abs(img.var() - expected_var) / expected_var < 0.05
    quiet = CameraConfig(read_noise_dn=0.0, shot_noise=False)
    assert np.array_equal(apply_detector_noise(signal, quiet, np.random.default_rng(0)), signal)
    a = apply_detector_noise(signal, cfg, np.random.default_rng(5))
    b = apply_detector_noise(signal, cfg, np.random.default_rng(5))
    assert np.array_equal(a, b)


@pytest.mark.parametrize("kw", [{}, {"shot_noise": False}, {"read_noise_dn": 0.0}, {"gain_e_per_dn": 3.0, "read_noise_dn": 7.5}])
def test_detector_noise_is_the_per_pixel_formula_for_uint8_and_float_signals(kw):
    # Independent: an explicit loop over pixels in float32 scalars, sigma = sqrt(max(S, 0) / gain + read^2),
    # S + sigma n rounded half to even and clipped to [0, 255]. Every uint8 level appears (the uint8 path looks
    # sigma up in a table of the 256 levels); the float path is the same formula on a non-integer signal.
    cfg = CameraConfig(**kw)
    rng = np.random.default_rng(3)
    levels = np.concatenate([np.arange(256), rng.integers(0, 256, 64)]).astype(np.uint8).reshape(16, 20)
    normal = (rng.standard_normal(levels.shape) * 4.0).astype(np.float32)  # large draws: the clip is reached
    exposed = np.clip(levels.astype(np.float32) * np.float32(1.37), 0.0, 255.0)
    for signal in (levels, exposed, levels[:, ::2]):  # the last: a strided view, as a colour channel is
        n = np.ascontiguousarray(normal[:, : signal.shape[1]])
        want = np.empty(signal.shape, np.uint8)
        for (i, j), s in np.ndenumerate(signal):
            var = np.float32(0.0)
            if cfg.shot_noise:
                var = var + np.float32(max(np.float32(s), np.float32(0.0))) * np.float32(1.0 / cfg.gain_e_per_dn)
            if cfg.read_noise_dn > 0:
                var = var + np.float32(cfg.read_noise_dn**2)
            value = np.float32(s) + np.float32(np.sqrt(var)) * n[i, j]
            want[i, j] = int(min(max(np.rint(value), 0.0), 255.0))
        assert np.array_equal(apply_detector_noise(signal, cfg, None, n), want)
        # The draws taken from the stream give the same frame as the same draws passed in.
        drawn = detector_normal(signal.shape, cfg, np.random.default_rng(9))
        if drawn is not None:
            assert np.array_equal(apply_detector_noise(signal, cfg, np.random.default_rng(9)),
                                  apply_detector_noise(signal, cfg, None, drawn))


def test_rendered_frame_has_texture_and_is_deterministic(posed_world):
    world, _ = posed_world
    a = world.render_signal()
    b = world.render_signal()
    assert a.dtype == np.uint8 and a.shape == (120, 160)
    assert np.array_equal(a, b)
    assert 30 < a.mean() < 220 and a.std() > 5


def _grad_rms(img: np.ndarray) -> float:
    g = img.astype(np.float64)
    gx = (g[1:-1, 2:] - g[1:-1, :-2]) / 2
    gy = (g[2:, 1:-1] - g[:-2, 1:-1]) / 2
    return float(np.sqrt((gx**2 + gy**2).mean()))


def test_landing_site_patch_keeps_fine_detail_at_the_vision_cutoff():
    from bench.sim.world_builder import place_above_target

    grads = {}
    for patch in (0.0, 96.0):
        sc = load_scenario(None, SMALL_SET + [f"terrain.patch_size_m={patch}", "terrain.patch_texture_px=1024"])
        with build_world(sc) as world:
            place_above_target(world, 30.0)
            grads[patch] = _grad_rms(world.render_signal())
    # Without the patch the 0.5 m texels are magnified ~4x at 30 m and the image is smooth.
    assert grads[96.0] > 1.5 * grads[0.0], grads
