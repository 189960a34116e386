"""One frame: raster G-buffer and local shading, ray-traced reflections of the
selected reflectors, compositing. ``raster/`` is OpenGL, ``trace/`` is Embree."""
