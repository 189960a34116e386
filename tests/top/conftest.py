"""Tests of what spans the phases: the CLI and its exit codes, the API, the cluster, the pytest
plugin, the kernels' cache, threads and the GL platform, the tools, the example stages
and the package layout.

Shared builders are the helper modules of tests/ (``scenes.py``, ...); fixtures every
phase uses are in tests/conftest.py."""
