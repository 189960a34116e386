"""Benchmarks only: exporting a scene to Mitsuba 3, the benchmark tools' stage set-up and
log entries. Never needed to render."""
