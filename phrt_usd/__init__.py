"""phrt-usd: heuristic hybrid rendering of USD stages (raster + selective ray-traced
reflections). Importing the package registers the Phrt USD schema plugin."""

import os

# pyrender/PyOpenGL pick their platform at import time: headless OSMesa unless the user
# chose otherwise.
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

__version__ = "0.1.0"
