"""The repository's folders, for tests that read them (stages, docs, the package's
sources) or run its tools: declared once, whatever folder a test module sits in."""

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGE = REPO / "phrt_usd"
STAGES = REPO / "stages"
TOOLS = REPO / "tools"
DOCS = REPO / "docs"
