"""OpenGL (pyrender on OSMesa): the G-buffer, shadow maps and the GPU
light pass, with their GLSL shaders."""
