"""Plain data the pipeline passes along: the scene, a frame's inputs and records.
No USD, OpenGL or Embree here; every other phase reads and fills these types."""
