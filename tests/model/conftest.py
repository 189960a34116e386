"""Tests of the plain data every phase passes along (phrt_usd/model/): the surface rule and its
kernels, the render option table.

Shared builders are the helper modules of tests/ (``scenes.py``, ...); fixtures every
phase uses are in tests/conftest.py."""
