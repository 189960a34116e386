"""OpenGL (pyrender on EGL or OSMesa, ``gl_platform``): the G-buffer, shadow maps and the
GPU light pass, with their GLSL shaders."""

import os

# PyOpenGL binds its platform when OpenGL is first imported. A render chooses it before
# that (``gl_platform.activate``: ``--gl auto`` picks EGL when a working EGL device is
# found, else OSMesa); OSMesa is the default for a caller that imports these modules
# without a render.
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
