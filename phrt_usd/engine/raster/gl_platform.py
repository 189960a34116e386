"""Which OpenGL platform the raster passes run on (``--gl``, ``RenderOptions.gl``).

* ``egl``: EGL's device platform, surfaceless (pyrender's ``EGLPlatform``): a GPU's
  driver where there is one, else Mesa's llvmpipe on the CPU through Mesa's EGL
  (Debian: libegl1, libegl-mesa0, libgbm1), so the same code runs on both.
* ``osmesa``: Mesa's off-screen OSMesa (llvmpipe, CPU only; Debian: libosmesa6).
* ``auto``: the platform OpenGL is already loaded with in this process, else the one
  named by ``PYOPENGL_PLATFORM`` in the environment phrt started in, else EGL when a
  working EGL device is found (``egl_problem``), else OSMesa.

PyOpenGL binds its platform when OpenGL is first imported (``PYOPENGL_PLATFORM``), so
the choice is the process's: ``activate`` sets it before any raster module imports
pyrender or OpenGL, and refuses another platform once OpenGL is loaded. This module
imports neither (the probe calls libEGL through ctypes).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

from phrt_usd.base import USER_GL_PLATFORM
from phrt_usd.errors import PhrtError
from phrt_usd.model.render_options import GL_PLATFORMS, OPTIONS  # noqa: F401

DEFAULT_GL = OPTIONS["gl"].default

# EGL enums (EGL 1.5 and EGL_EXT_platform_device), as in Khronos' egl.h / eglext.h.
EGL_NONE = 0x3038
EGL_SURFACE_TYPE = 0x3033
EGL_PBUFFER_BIT = 0x0001
EGL_RENDERABLE_TYPE = 0x3040
EGL_OPENGL_BIT = 0x0008
EGL_OPENGL_API = 0x30A2
EGL_PLATFORM_DEVICE_EXT = 0x313F
EGL_CONTEXT_MAJOR_VERSION = 0x3098
EGL_CONTEXT_MINOR_VERSION = 0x30FB
EGL_CONTEXT_OPENGL_PROFILE_MASK = 0x30FD
EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT = 0x0001
#: The OpenGL version pyrender's EGL platform asks for (core profile).
EGL_GL_VERSION = (4, 1)

_state: dict[str, object] = {"egl_problem": ...}  # ... : not probed yet


def check_gl(value: object) -> str:
    """``value`` as one of GL_PLATFORMS; BadOption (one line) otherwise."""
    return OPTIONS["gl"].check(value)


def loaded_platform() -> str | None:
    """The platform OpenGL was imported with in this process, None before its import."""
    if "OpenGL" not in sys.modules:
        return None
    return os.environ.get("PYOPENGL_PLATFORM", "").lower() or None


def resolve(requested: str) -> str:
    """The platform ``requested`` (one of GL_PLATFORMS) runs on here: ``egl`` or
    ``osmesa`` (see the module docstring for ``auto``)."""
    requested = check_gl(requested)
    if requested != "auto":
        return requested
    loaded = loaded_platform()
    if loaded in ("egl", "osmesa"):
        return loaded
    chosen = (USER_GL_PLATFORM or "").lower()
    if chosen in ("egl", "osmesa"):
        return chosen
    return "egl" if egl_problem() is None else "osmesa"


def activate(requested: str) -> str:
    """Resolve ``requested`` and make it the platform OpenGL loads with; returns it.
    PhrtError (one line) when OpenGL is already loaded with another platform or ``egl``
    has no working device here."""
    platform = resolve(requested)
    loaded = loaded_platform()
    if loaded is not None and loaded != platform:
        raise PhrtError(
            f"--gl {platform}: OpenGL is already loaded with {loaded} in this process "
            "(the platform is chosen once per process, before the first render)"
        )
    if platform == "egl" and loaded is None:
        problem = egl_problem()
        if problem is not None:
            raise PhrtError(f"--gl egl: no working EGL device here: {problem}")
    os.environ["PYOPENGL_PLATFORM"] = platform
    return platform


def egl_problem() -> str | None:
    """None when an EGL device display initialises, offers an OpenGL pbuffer config and
    creates an OpenGL EGL_GL_VERSION core context; else why not (one line). Probed once
    per process, through ctypes (no OpenGL import)."""
    if _state["egl_problem"] is ...:
        _state["egl_problem"] = _probe_egl()
    return _state["egl_problem"]  # type: ignore[return-value]


def _probe_egl() -> str | None:
    name = ctypes.util.find_library("EGL")
    if name is None:
        return "libEGL not found (Debian: libegl1 libegl-mesa0 libgbm1)"
    try:
        egl = ctypes.CDLL(name)
    except OSError as exc:
        return f"{name}: {exc}"
    vp, i32 = ctypes.c_void_p, ctypes.c_int32
    egl.eglGetProcAddress.restype = vp
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    egl.eglGetDisplay.restype = vp
    egl.eglGetDisplay.argtypes = [vp]
    egl.eglInitialize.argtypes = [vp, ctypes.POINTER(i32), ctypes.POINTER(i32)]
    egl.eglBindAPI.argtypes = [ctypes.c_uint]
    egl.eglChooseConfig.argtypes = [vp, ctypes.POINTER(i32), ctypes.POINTER(vp), i32,
                                    ctypes.POINTER(i32)]  # fmt: skip
    egl.eglCreateContext.restype = vp
    egl.eglCreateContext.argtypes = [vp, vp, vp, ctypes.POINTER(i32)]
    egl.eglDestroyContext.argtypes = [vp, vp]
    egl.eglTerminate.argtypes = [vp]
    display = _device_display(egl)
    if not display:
        return "no EGL display (no device, and no default display)"
    major, minor = i32(), i32()
    if not egl.eglInitialize(display, ctypes.byref(major), ctypes.byref(minor)):
        return "eglInitialize failed"
    try:
        if not egl.eglBindAPI(EGL_OPENGL_API):
            return "the EGL display offers no desktop OpenGL"
        attributes = (i32 * 5)(EGL_SURFACE_TYPE, EGL_PBUFFER_BIT, EGL_RENDERABLE_TYPE,
                               EGL_OPENGL_BIT, EGL_NONE)  # fmt: skip
        config, count = vp(), i32()
        chosen = egl.eglChooseConfig(
            display, attributes, ctypes.byref(config), 1, ctypes.byref(count)
        )
        if not chosen or count.value < 1:
            return "no OpenGL pbuffer config on the EGL display"
        context_attributes = (i32 * 7)(
            EGL_CONTEXT_MAJOR_VERSION, EGL_GL_VERSION[0],
            EGL_CONTEXT_MINOR_VERSION, EGL_GL_VERSION[1],
            EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT,
            EGL_NONE,
        )  # fmt: skip
        context = egl.eglCreateContext(display, config, None, context_attributes)
        if not context:
            major_minor = ".".join(map(str, EGL_GL_VERSION))
            return f"the EGL display creates no OpenGL {major_minor} core context"
        egl.eglDestroyContext(display, context)
        return None
    finally:
        egl.eglTerminate(display)


def _device_display(egl) -> int | None:
    """The first EGL device's display (EGL_EXT_device_enumeration), as pyrender's
    ``EGLPlatform`` picks it; without that extension the default display."""
    vp, i32 = ctypes.c_void_p, ctypes.c_int32
    query = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
    platform_display = egl.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
    if not query or not platform_display:
        return egl.eglGetDisplay(None)
    query_devices = ctypes.CFUNCTYPE(ctypes.c_uint, i32, ctypes.POINTER(vp),
                                     ctypes.POINTER(i32))(query)  # fmt: skip
    get_display = ctypes.CFUNCTYPE(vp, ctypes.c_uint, vp, ctypes.POINTER(i32))(platform_display)
    device, count = vp(), i32()
    if not query_devices(1, ctypes.byref(device), ctypes.byref(count)) or count.value < 1:
        return None
    return get_display(EGL_PLATFORM_DEVICE_EXT, device, None)


def make_platform(platform: str, width: int, height: int):
    """pyrender's platform object of ``platform`` (``egl`` / ``osmesa``, as ``activate``
    returned it) for a ``width`` x ``height`` context, not yet initialised."""
    if platform == "egl":
        return _egl_platform_class()(width, height)
    from pyrender.platforms.osmesa import OSMesaPlatform

    return OSMesaPlatform(width, height)


def _egl_platform_class():
    """pyrender's EGLPlatform, except that contexts share the device's display: EGL
    hands every caller the same display of a device, and pyrender terminates it with
    each context (which kills the others' contexts), so here the last context alive
    terminates it. One class per process (it counts the live contexts)."""
    if "egl_class" in _state:
        return _state["egl_class"]
    from pyrender.platforms.egl import EGLPlatform

    class SharedDisplayEGLPlatform(EGLPlatform):
        live = 0  # contexts of this process not yet deleted

        def init_context(self) -> None:
            super().init_context()
            SharedDisplayEGLPlatform.live += 1

        def delete_context(self) -> None:
            from OpenGL.EGL import (
                EGL_NO_CONTEXT,
                EGL_NO_SURFACE,
                eglDestroyContext,
                eglMakeCurrent,
                eglTerminate,
            )

            if self._egl_display is None:
                return
            if self._egl_context is not None:
                eglMakeCurrent(self._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
                eglDestroyContext(self._egl_display, self._egl_context)
                self._egl_context = None
                SharedDisplayEGLPlatform.live -= 1
            if SharedDisplayEGLPlatform.live == 0:
                eglTerminate(self._egl_display)
            self._egl_display = None

    _state["egl_class"] = SharedDisplayEGLPlatform
    return SharedDisplayEGLPlatform
