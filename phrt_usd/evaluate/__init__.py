"""Measuring runs: selection metrics and reports, image error, sweeps of
heuristic x budget and their summary, plots and HTML report."""
