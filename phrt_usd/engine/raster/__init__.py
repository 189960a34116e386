"""OpenGL (pyrender on OSMesa): the G-buffer, shadow maps and the GPU
light pass, with their GLSL shaders."""

import os

# PyOpenGL picks its platform when OpenGL is first imported: before any module of this
# package imports pyrender / OpenGL.
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
