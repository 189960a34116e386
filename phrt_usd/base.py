"""What every phase may read of the package itself: its version, and the OpenGL platform
this process imports OpenGL with unless a render chooses one.

PyOpenGL binds its platform when OpenGL is first imported (``PYOPENGL_PLATFORM``). A
render chooses it before that (``--gl``; auto: EGL when a working EGL device is found,
else OSMesa: ``phrt_usd.engine.raster.gl_platform``); OSMesa is the headless default for
OpenGL imported without a render. What the user chose, if anything, is kept in
``USER_GL_PLATFORM`` for ``--gl auto``. The package root imports this module first, so
the default holds before any module of the package imports OpenGL. This module imports
nothing of the package.
"""

import os

__version__ = "0.1.0"

#: ``PYOPENGL_PLATFORM`` as the environment phrt started in had it (None: not set).
USER_GL_PLATFORM = os.environ.get("PYOPENGL_PLATFORM")
#: The platform of imports outside a render when the user chose none: OSMesa needs no
#: display and no device.
DEFAULT_IMPORT_GL_PLATFORM = "osmesa"
os.environ.setdefault("PYOPENGL_PLATFORM", DEFAULT_IMPORT_GL_PLATFORM)
