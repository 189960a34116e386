"""Tests of one frame (phrt_usd/engine/): the G-buffer, shading, shadow maps, the tracer and its
kernels, cut-outs, sparse pixels, scene changes, motion and whole frames.

Shared builders are the helper modules of tests/ (``scenes.py``, ...); fixtures every
phase uses are in tests/conftest.py."""
