"""GL backend selection happens before mujoco is imported and fails with one clear error."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from models import gl


def _probe(env_update: dict[str, str | None]) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    for k, v in env_update.items():
        if v is None:
            env.pop(k, None)
        else:
            env[k] = v
    code = "from models.gl import ensure_gl_backend; b = ensure_gl_backend(); import os; print(b, os.environ['MUJOCO_GL'])"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)


def test_user_choice_is_respected():
    res = _probe({"MUJOCO_GL": "osmesa"})
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["osmesa", "osmesa"]


# Renders a tiny scene with MuJoCo alone (models.gl is not imported): a backend "really works"
# when a context can be made and a frame read back.
_RENDER_TINY_SCENE = """
import mujoco
model = mujoco.MjModel.from_xml_string(
    '<mujoco><worldbody><light pos="0 0 3"/><geom type="sphere" size="0.5" rgba="1 0 0 1"/></worldbody></mujoco>')
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)
renderer = mujoco.Renderer(model, 16, 16)
renderer.update_scene(data)
image = renderer.render()
renderer.close()
assert image.shape == (16, 16, 3) and image.max() > 0, (image.shape, image.max())
print("rendered")
"""


def _renders_with(backend: str) -> bool:
    """Whether MuJoCo renders with MUJOCO_GL (and PYOPENGL_PLATFORM) set to ``backend``, in a fresh process."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env.update(MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    res = subprocess.run([sys.executable, "-c", _RENDER_TINY_SCENE], env=env, capture_output=True, text=True,
                         timeout=120)
    return res.returncode == 0 and res.stdout.strip() == "rendered"


def test_default_prefers_egl_when_it_works():
    res = _probe({"MUJOCO_GL": None, "PYOPENGL_PLATFORM": None})
    # The expectation comes from rendering, not from the module's own probes.
    egl, osmesa = _renders_with("egl"), _renders_with("osmesa")
    if not (egl or osmesa):
        assert res.returncode != 0 and "GLBackendError" in res.stderr, (res.stdout, res.stderr)
        return
    assert res.returncode == 0, res.stderr
    expected = "egl" if egl else "osmesa"
    assert res.stdout.split() == [expected, expected]


def _isolated_env(monkeypatch):
    # ensure_gl_backend writes os.environ; give it a throwaway copy.
    env = dict(os.environ)
    env.pop("MUJOCO_GL", None)
    monkeypatch.setattr(os, "environ", env)
    return env


def test_no_backend_names_the_packages(monkeypatch):
    _isolated_env(monkeypatch)
    monkeypatch.setattr(gl, "_chosen", None)
    monkeypatch.setattr(gl, "_egl_works", lambda: False)
    monkeypatch.setattr(gl, "_osmesa_works", lambda: False)
    with pytest.raises(gl.GLBackendError) as exc:
        gl.ensure_gl_backend()
    msg = str(exc.value)
    assert "\n" not in msg
    for pkg in ("libegl1", "libegl-mesa0", "libgl1-mesa-dri", "libosmesa6"):
        assert pkg in msg


def test_osmesa_fallback(monkeypatch):
    env = _isolated_env(monkeypatch)
    monkeypatch.setattr(gl, "_chosen", None)
    monkeypatch.setattr(gl, "_egl_works", lambda: False)
    monkeypatch.setattr(gl, "_osmesa_works", lambda: True)
    assert gl.ensure_gl_backend() == "osmesa"
    assert env["MUJOCO_GL"] == "osmesa" and env["PYOPENGL_PLATFORM"] == "osmesa"


def test_probing_egl_does_not_break_rendering_in_the_same_process():
    # EGL returns one shared display per device; a probe that terminated it would make
    # every later MuJoCo context fail with EGL_NOT_INITIALIZED.
    from tests.conftest import make_terrain
    import numpy as np
    from models.camera import CameraConfig
    from models.lander import LanderConfig
    from models.world import SunConfig, World

    def render_once():
        w = World(make_terrain(np.zeros((17, 17)), 64.0), LanderConfig(), CameraConfig(width_px=32, height_px=32),
                  SunConfig(), 2_000_000)
        img = w.render_signal()
        w.close()
        return img

    render_once()
    gl._egl_works()
    assert render_once().shape == (32, 32)
