"""Fixtures of the evaluate phase's tests (reports, sweeps, image and temporal metrics)."""

from __future__ import annotations

from pathlib import Path

import pytest
from synthetic_sweep import write_synthetic_sweep

from phrt_usd.evaluate.sweep_report import write_sweep_report


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory) -> Path:
    """A synthetic sweep (``synthetic_sweep.py``) with its report written beside it
    (summary.md, plots, report.html), once per test module."""
    out = write_synthetic_sweep(tmp_path_factory.mktemp("sweep"))
    write_sweep_report(out)
    return out
