"""The camera's off-screen renderer, with its GL resources shared between worlds that look alike.

Ports:
    Input: a MuJoCo model and data, the camera id, at the camera rate.
    Output: the rendered grayscale frame, (H, W) uint8 [DN].
    Rate: on request (``World.render_signal``).

Building MuJoCo's render context (``MjrContext``) uploads every texture, heightfield and
mesh of the model, the 4096² terrain texture and its mipmaps included, in a new GL context
whose shaders the driver compiles anew: together about 0.3 s of a world's first frame. Worlds
built one after another in a process (Gymnasium resets, tests, a campaign whose terrain is not
dispersed) often fly over the same terrain with the same camera. Here the GL context and the
render context are kept in the process, keyed by a digest of everything ``mjr_makeContext``
reads from the model (textures, heightfields, meshes, skins, flexes, the materials' texture
bindings, the visual block, the model's extent and its planes) and the frame size, and a world
whose model gives the same digest renders through them: the same uploaded data, so the same
pixels. Each world keeps its own ``MjvScene`` (the geoms of its own model).

A context is shared by the worlds of one thread alive with that digest (a world of another
thread gets its own) and, when the last of them is closed, kept idle for the next world of any
thread. A world with other assets takes over the idle context's GL context (its assets
replaced; the driver's compiled shaders are kept, about 0.1 s a world); any other idle context
is freed then. A context is current only during a call, never between calls. A context made in
another process (a fork) is never used or freed here: its GL state did not survive the fork.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from models.gl import ensure_gl_backend

ensure_gl_backend()
import mujoco  # noqa: E402  (the GL backend must be chosen first)

# MuJoCo's Python Renderer's defaults, kept so the frames are the same.
MAX_GEOM = 10000
CULL_MARGIN = 0.02  # widening of the view pyramid's half-angle tangents when culling geoms (CameraRenderer)
FONT_SCALE = mujoco.mjtFontScale.mjFONTSCALE_150

# Model arrays mjr_makeContext (and mjr_render's use of the context) depend on.
_ASSET_PREFIXES = ("tex_", "hfield_", "mesh_", "skin_", "flex_")
_MATERIAL_FIELDS = ("mat_texid", "mat_texuniform", "mat_texrepeat")
_VIS_BLOCKS = ("global_", "quality", "map", "scale", "rgba", "headlight")


def _struct_bytes(obj: object) -> bytes:
    """The public numeric fields of a MuJoCo struct (the vis blocks), in name order."""
    parts = []
    for name in sorted(a for a in dir(obj) if not a.startswith("_")):
        value = getattr(obj, name)
        if callable(value):
            continue
        parts.append(name.encode() + b"=" + np.asarray(value).tobytes())
    return b";".join(parts)


def _array_digest(h: "hashlib._Hash", name: str, value: object) -> None:
    arr = np.ascontiguousarray(value)
    h.update(f"{name}:{arr.dtype.str}:{arr.shape};".encode())
    if arr.size:
        h.update(memoryview(arr.reshape(-1)).cast("B"))


def arrays_digest(arrays: Sequence[np.ndarray]) -> bytes:
    """A digest of arrays' dtypes, shapes and bytes, in order (e.g. the pixels a world writes into its
    model's textures, for :class:`CameraRenderer`'s ``texture_key``)."""
    h = hashlib.sha256()
    for i, a in enumerate(arrays):
        _array_digest(h, str(i), a)
    return h.digest()


def visual_digest(model: mujoco.MjModel, width: int, height: int, texture_key: bytes | None = None) -> bytes:
    """A digest of what a render context built from ``model`` holds, and of the frame size.

    Two models with the same digest give render contexts with the same textures,
    heightfields, meshes, material bindings, fog, shadow and buffer settings.

    Args:
        texture_key: A digest of the texture pixels from whoever wrote them, used in place of
            ``tex_data`` itself (63 MB for the default terrain: about 45 ms to hash); None hashes it.
    """
    h = hashlib.sha256()
    h.update(f"{mujoco.__version__};{width}x{height};{int(FONT_SCALE)}".encode())
    names = sorted(a for a in dir(model) if a.startswith(_ASSET_PREFIXES)) + list(_MATERIAL_FIELDS)
    for name in names:
        value = getattr(model, name)
        if name != "tex_data" and not callable(value):
            _array_digest(h, name, value)
    for block in _VIS_BLOCKS:
        h.update(block.encode() + _struct_bytes(getattr(model.vis, block)))
    # mjr_makeContext reads the model's statistics only for its extent (fog, shadow clip, and the
    # grid of infinite planes), and the geoms only for the planes' grids.
    h.update(b"extent" + np.float64(model.stat.extent).tobytes())
    planes = np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)
    _array_digest(h, "plane_size", model.geom_size[planes])
    _array_digest(h, "plane_matid", model.geom_matid[planes])
    if texture_key is None:
        _array_digest(h, "tex_data", model.tex_data)
    else:
        h.update(b"texture_key" + texture_key)
    return h.digest()


class _SharedContext:
    """One GL context and the MuJoCo render context built in it.

    It is made current only for the duration of a call (:meth:`current`) and left current in
    no thread between calls, so that a world in another thread (a Gymnasium episode runs in a
    thread of its own) can take it over once its last user has closed, or free it.
    """

    def __init__(self, key: bytes, model: mujoco.MjModel, width: int, height: int):
        self.pid = os.getpid()
        self.size = (width, height)
        self.thread: int | None = None  # the thread whose worlds use it; None while idle
        self.users = 0
        # What its frame buffer holds, started by CameraRenderer.start and not read yet: (renderer,
        # frame key); None when it holds no such frame.
        self.started: tuple | None = None
        self.gl = mujoco.GLContext(width, height)
        # mujoco.GLContext.as_current (MuJoCo >= 3.3) restores the thread's previous context,
        # none included, afterwards; without it the context stays current in its thread, so
        # it is private to its world (freed with it, never kept idle).
        self.shareable = hasattr(self.gl, "as_current")
        self.mjr = None
        self.rebuild(key, model)

    def rebuild(self, key: bytes, model: mujoco.MjModel) -> None:
        """Upload another model's assets into this GL context (freeing the ones it holds).

        Keeping the GL context keeps what the driver compiled for it (llvmpipe's shader
        variants): about 0.1 s of a new context and its first frames, here. The frames are the
        same as a new context's (tested)."""
        with self.current():
            if self.mjr is not None:
                self.mjr.free()
            self.mjr = mujoco.MjrContext(model, FONT_SCALE.value)
            self.started = None
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self.mjr)
            self.mjr.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self.key = key

    def current(self) -> contextlib.AbstractContextManager:
        if self.shareable:
            return self.gl.as_current()
        self.gl.make_current()
        return contextlib.nullcontext()

    def free(self) -> None:
        if self.pid != os.getpid():
            return  # a fork's copy: the GL objects belong to the parent
        with self.current():
            self.mjr.free()
        self.gl.free()


# This process's contexts; at most one of them idle (no user), the most recently released.
_CONTEXTS: list[_SharedContext] = []
_LOCK = threading.Lock()


def _acquire(model: mujoco.MjModel, width: int, height: int,
             texture_key: bytes | None) -> _SharedContext:
    key = visual_digest(model, width, height, texture_key)
    me = threading.get_ident()
    with _LOCK:
        if any(c.pid != os.getpid() for c in _CONTEXTS):
            _CONTEXTS.clear()  # inherited through a fork: none of them is usable here
        # A context in use serves only its own thread's worlds (two threads never share one).
        ctx = next((c for c in _CONTEXTS if c.key == key and c.shareable and (c.users == 0 or c.thread == me)),
                   None)
        if ctx is None:
            # Another model: the idle context's GL context takes its assets, when its size fits.
            idle = next((c for c in _CONTEXTS if c.users == 0 and c.size == (width, height)), None)
            _free_idle(keep=idle)
            if idle is not None:
                idle.rebuild(key, model)
                ctx = idle
            else:
                ctx = _SharedContext(key, model, width, height)
                _CONTEXTS.append(ctx)
        ctx.users += 1
        ctx.thread = me
    return ctx


def _release(ctx: _SharedContext) -> None:
    with _LOCK:
        ctx.users -= 1
        assert ctx.users >= 0, "render context released more often than acquired"
        if ctx.users == 0:
            ctx.thread = None
            if ctx.shareable:  # kept for the next world (a campaign's next case); any other idle one freed
                _free_idle(keep=ctx)
            else:
                _CONTEXTS.remove(ctx)
                ctx.free()


def _free_idle(keep: _SharedContext | None = None) -> None:
    for c in [c for c in _CONTEXTS if c.users == 0 and c is not keep]:
        _CONTEXTS.remove(c)
        c.free()


def free_shared_contexts() -> int:
    """Free the idle render contexts of this process; returns how many were freed."""
    with _LOCK:
        n = sum(c.users == 0 for c in _CONTEXTS)
        _free_idle()
    return n


@dataclass(frozen=True)
class CulledGeoms:
    """Geoms a :class:`CameraRenderer` draws only in frames whose view they may reach.

    Attributes:
        geom_ids: (K,) the geoms (static: their bounding boxes do not move).
        corners: (K, 8, 3) the corners of each geom's bounding box in the world frame [m].
        group: The geom group they are drawn in (the renderer shows it).
        hidden_group: The group a geom is moved to for a frame it cannot appear in (the renderer hides it).
        replaces_group: A group the renderer hides because these geoms draw what it holds.
    """

    geom_ids: np.ndarray
    corners: np.ndarray
    group: int
    hidden_group: int
    replaces_group: int

    def show_in(self, option: mujoco.MjvOption) -> None:
        """Set ``option`` to draw these geoms' group instead of the group they replace (hidden ones not)."""
        option.geomgroup[self.replaces_group] = 0
        option.geomgroup[self.group] = 1
        option.geomgroup[self.hidden_group] = 0


def gl_function(name: str, restype: object, *argtypes: object) -> Callable:
    """An OpenGL function of the GL library MuJoCo's context runs on, as a ctypes function.

    Taken from PyOpenGL's platform object (imported with MuJoCo's EGL or OSMesa context), not from
    ``OpenGL.GL``, whose import costs about 0.1 s for a function or two.
    """
    import ctypes

    from OpenGL import platform  # PyOpenGL, MuJoCo's own dependency for EGL and OSMesa

    return ctypes.CFUNCTYPE(restype, *argtypes)((name, platform.PLATFORM.GL))


_GL_FLUSH: Callable | None = None


def _gl_flush() -> None:
    """``glFlush``: hand the GL commands issued so far to the driver, without waiting for them."""
    global _GL_FLUSH
    if _GL_FLUSH is None:
        _GL_FLUSH = gl_function("glFlush", None)
    _GL_FLUSH()


class CameraRenderer:
    """Renders one model's camera through a shared render context.

    The same calls, in the same order, as ``mujoco.Renderer``'s ``update_scene`` and
    ``render`` with a fixed camera (``mjv_updateScene`` with every category, then
    ``mjr_render`` and ``mjr_readPixels`` into the off-screen buffer, flipped to image rows).

    Args:
        model: The world's model.
        width: Frame width [px].
        height: Frame height [px].
        texture_key: A digest of the model's texture pixels (``tex_data``) from whoever wrote
            them (the world: its terrain's albedo), so that 63 MB need not be hashed for every
            world; None hashes ``tex_data`` itself.
        culled: Geoms drawn only when their bounding box may be in the camera's view (the
            terrain's tiles): before each frame, those wholly outside one side of the view
            pyramid are moved to their hidden group (``model.geom_group``, which nothing but
            drawing reads for them). The frame is the same as with all of them drawn.
    """

    def __init__(self, model: mujoco.MjModel, width: int, height: int, texture_key: bytes | None = None,
                 culled: CulledGeoms | None = None):
        if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
            raise ValueError(f"a {width}x{height} frame does not fit the model's off-screen buffer "
                             f"({model.vis.global_.offwidth}x{model.vis.global_.offheight})")
        self._model = model
        self._ctx: _SharedContext | None = _acquire(model, width, height, texture_key)
        self._scene = mujoco.MjvScene(model=model, maxgeom=MAX_GEOM)
        self._option = mujoco.MjvOption()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._rgb = np.empty((height, width, 3), np.uint8)
        self._culled = culled
        if culled is not None:
            culled.show_in(self._option)
            self._aspect = width / height  # MuJoCo's view: fovy vertical, the frame's aspect horizontal

    def _cull(self, data: mujoco.MjData, camera_id: int) -> None:
        """Move the culled geoms wholly outside the camera's view pyramid to their hidden group."""
        c = self._culled
        # The view pyramid's half-angle tangents, widened by CULL_MARGIN: a geom is left out only when clearly outside.
        tan_y = math.tan(math.radians(float(self._model.cam_fovy[camera_id])) / 2.0) * (1.0 + CULL_MARGIN)
        tan_x = tan_y * self._aspect
        # Box corners in the camera frame (x right, y up, looking along -z); depth along the view.
        v = (c.corners - data.cam_xpos[camera_id]) @ data.cam_xmat[camera_id].reshape(3, 3)
        x, y, depth = v[..., 0], v[..., 1], -v[..., 2]
        # The pyramid is the intersection of four half-spaces through the camera's centre; a box whose
        # corners all lie outside one of them lies outside it (behind the camera included).
        out = ((x > tan_x * depth).all(axis=1) | (x < -tan_x * depth).all(axis=1)
               | (y > tan_y * depth).all(axis=1) | (y < -tan_y * depth).all(axis=1))
        self._model.geom_group[c.geom_ids] = np.where(out, c.hidden_group, c.group)

    def render_green(self, data: mujoco.MjData, camera_id: int) -> np.ndarray:
        """The frame's green channel, (H, W) uint8, image row 0 at the top (:meth:`draw`, then :meth:`read_green`)."""
        self.draw(data, camera_id)
        return self.read_green()

    def start(self, data: mujoco.MjData, camera_id: int) -> None:
        """:meth:`draw` a frame of ``data`` as it is now, to be read by :meth:`read_green`, unless the
        context's frame buffer already holds it: started here, not read yet, of the same camera and
        the same poses (the joints, the camera and every geom), and no renderer sharing the context
        has drawn since. Starting a frame that is never read costs only its drawing."""
        d = data
        key = (camera_id, b"".join(a.tobytes() for a in (d.qpos, d.cam_xpos, d.cam_xmat, d.geom_xpos, d.geom_xmat)))
        held = self._ctx.started if self._ctx is not None else None
        if held is None or held[0] is not self or held[1] != key:
            self.draw(data, camera_id)
            self._ctx.started = (self, key)

    def draw(self, data: mujoco.MjData, camera_id: int) -> None:
        """Draw a frame of ``data`` as it is now, and hand it to the GL driver without waiting for it.

        ``glFlush`` after ``mjr_render``: a CPU renderer (llvmpipe) rasterises the frame on its own
        threads while the caller goes on; :meth:`read_green` then waits for what is left. Without
        the flush llvmpipe starts only when the pixels are read. The pixels are the same.
        """
        if self._ctx is None:
            raise RuntimeError("render called after close")
        self._camera.fixedcamid = camera_id
        if self._culled is not None:
            self._cull(data, camera_id)
        mujoco.mjv_updateScene(self._model, data, self._option, None, self._camera,
                               mujoco.mjtCatBit.mjCAT_ALL.value, self._scene)
        with self._ctx.current():
            mujoco.mjr_render(self._rect, self._scene, self._ctx.mjr)
            _gl_flush()
        self._ctx.started = None  # the frame buffer no longer holds a started frame

    def read_green(self) -> np.ndarray:
        """The green channel of the frame last drawn (:meth:`draw`), (H, W) uint8, image row 0 at the top."""
        if self._ctx is None:
            raise RuntimeError("render called after close")
        with self._ctx.current():
            mujoco.mjr_readPixels(self._rgb, None, self._rect, self._ctx.mjr)
        self._ctx.started = None  # read: the next start draws again
        return np.ascontiguousarray(self._rgb[::-1, :, 1])

    def current(self) -> contextlib.AbstractContextManager:
        """This renderer's GL context, current for a ``with`` block (to query it)."""
        return self._ctx.current()

    def close(self) -> None:
        """Give the shared context back (freed with its last user, unless kept idle)."""
        if self._ctx is not None:
            ctx, self._ctx = self._ctx, None
            if ctx.started is not None and ctx.started[0] is self:
                ctx.started = None
            if ctx.pid == os.getpid():
                _release(ctx)

    def __del__(self) -> None:
        # A world dropped without close(): give the context back, as mujoco.Renderer frees its own.
        with contextlib.suppress(Exception):
            self.close()
