"""Headless OpenGL backend selection for MuJoCo's off-screen renderer.

MuJoCo reads ``MUJOCO_GL`` once, when ``mujoco`` is first imported, so the
choice has to be made before that import. :func:`ensure_gl_backend` is called
by every module of ``models/`` that imports mujoco, before the import.

Policy:
    1. A ``MUJOCO_GL`` the user has already set is respected as is.
    2. Otherwise EGL, when ``libEGL`` loads and a display initialises
       (Mesa's llvmpipe works without a GPU).
    3. Otherwise OSMesa, when ``libOSMesa`` loads.
    4. Otherwise one :class:`GLBackendError` that names the Debian packages
       to install.

``PYOPENGL_PLATFORM`` is set to match, because PyOpenGL (used by MuJoCo's
context classes) picks its platform on its own import.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

# Debian/Ubuntu packages that provide each backend (what `make` installs).
EGL_PACKAGES = ("libegl1", "libegl-mesa0", "libgl1-mesa-dri")
OSMESA_PACKAGES = ("libosmesa6",)

_EGL_PLATFORM_DEVICE_EXT = 0x313F
_MAX_EGL_DEVICES = 16
_chosen: str | None = None


class GLBackendError(RuntimeError):
    """No headless OpenGL backend could be found."""


def _egl_works() -> bool:
    """True when libEGL loads and an EGL device display initialises.

    Mirrors what MuJoCo's EGL context does: enumerate devices with
    ``eglQueryDevicesEXT`` and open one through the device platform (Mesa
    offers a software device, so this works without a GPU or X server).
    """
    name = ctypes.util.find_library("EGL") or "libEGL.so.1"
    try:
        egl = ctypes.CDLL(name)
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
        egl.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
        query_ptr = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
        display_ptr = egl.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
    except (OSError, AttributeError):
        return False
    if not query_ptr or not display_ptr:
        return False
    query_devices = ctypes.CFUNCTYPE(
        ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_int)
    )(query_ptr)
    get_display = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p)(display_ptr)
    devices = (ctypes.c_void_p * _MAX_EGL_DEVICES)()
    count = ctypes.c_int()
    if not query_devices(_MAX_EGL_DEVICES, devices, ctypes.byref(count)):
        return False
    for i in range(count.value):
        display = get_display(_EGL_PLATFORM_DEVICE_EXT, devices[i], None)
        # Not terminated afterwards: EGL hands every caller the same display for a
        # device, and terminating it would break MuJoCo's contexts in this process.
        if display and egl.eglInitialize(display, None, None):
            return True
    return False


def _osmesa_works() -> bool:
    """True when libOSMesa loads."""
    for name in (ctypes.util.find_library("OSMesa"), "libOSMesa.so.8", "libOSMesa.so.6"):
        if not name:
            continue
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


def ensure_gl_backend() -> str:
    """Choose MuJoCo's GL backend, set the environment, and return its name.

    Idempotent and cheap after the first call.

    Returns:
        The backend name: ``"egl"``, ``"osmesa"`` or the user's own ``MUJOCO_GL``.

    Raises:
        GLBackendError: Neither EGL nor OSMesa is usable. The message names the
            packages that provide them.
    """
    global _chosen
    if _chosen is not None:
        return _chosen
    user = os.environ.get("MUJOCO_GL")
    if user:
        _chosen = user
        if user in ("egl", "osmesa"):
            os.environ.setdefault("PYOPENGL_PLATFORM", user)
        return _chosen
    if _egl_works():
        _chosen = "egl"
    elif _osmesa_works():
        _chosen = "osmesa"
    else:
        raise GLBackendError(
            "no headless OpenGL backend: EGL did not initialise and OSMesa is not installed. "
            f"Install Mesa's EGL ({' '.join(EGL_PACKAGES)}) or OSMesa ({' '.join(OSMESA_PACKAGES)}), "
            f"e.g. `sudo apt-get install {' '.join(EGL_PACKAGES + OSMESA_PACKAGES)}`, "
            "or set MUJOCO_GL to a backend that works here."
        )
    os.environ["MUJOCO_GL"] = _chosen
    os.environ["PYOPENGL_PLATFORM"] = _chosen
    return _chosen
