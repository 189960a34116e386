"""Tests of reading and writing USD (phrt_usd/usd/): stages, cameras, geometry, lights, materials
and textures, the schema, validation and authoring.

Shared builders are the helper modules of tests/ (``scenes.py``, ...); fixtures every
phase uses are in tests/conftest.py."""
