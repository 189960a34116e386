"""Peer benchmarks only: exporting a scene to Mitsuba 3. Never needed to render."""
