"""Tests of choosing the reflectors to trace (phrt_usd/select/): the metrics, HEU1/HEU2/HEU3, the
round loop, the cost model and the selection graph; mostly on fake frames
(``selection_fakes.py``).

Shared builders are the helper modules of tests/ (``scenes.py``, ...); fixtures every
phase uses are in tests/conftest.py."""
