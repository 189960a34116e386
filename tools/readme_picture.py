"""The picture at the top of the README: one frame of the demo stage in raster, hybrid
and rt, side by side, each labelled, as one PNG.

    uv run python tools/readme_picture.py [--frame 571] [--out docs/demo_modes.png]

Renders the frame with ``phrt render`` in each mode (hybrid with HEU1 and an unbounded
budget, so every reflector in view is traced) into a temporary directory, then joins the
PNG previews left to right with a one-line label under each.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from phrt_usd.run.images import read_preview_png, write_png_atomic

ROOT = Path(__file__).resolve().parent.parent
STAGE = ROOT / "stages" / "farm.usda"
MODES = ("raster", "hybrid", "rt")
RESOLUTION = "320x240"
#: Gap between panels and the label strip's height, in pixels.
GAP, LABEL_HEIGHT = 4, 20


def render_mode(mode: str, frame: float, out: Path) -> np.ndarray:
    cmd = [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "-q", "render", str(STAGE),
           "--out", str(out), "--frames", f"{frame:g}", "--mode", mode, "--budget-ms", "inf",
           "--resolution", RESOLUTION, "--json"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"{mode}: {done.stderr.strip()}")
    return read_preview_png(next((out / "frames").glob("*.png")))


def label(text: str, width: int) -> np.ndarray:
    """(LABEL_HEIGHT, width, 3) uint8: ``text`` in white on dark grey (matplotlib's
    text rendering, so no font file is needed)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig = plt.figure(figsize=(width / 100, LABEL_HEIGHT / 100), dpi=100)
    fig.patch.set_facecolor((0.15, 0.15, 0.15))
    fig.text(0.5, 0.5, text, color="white", ha="center", va="center", fontsize=9)
    fig.canvas.draw()
    pixels = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return pixels


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frame", type=float, default=560.0, help="time code (reflectors in view)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "demo_modes.png")
    args = ap.parse_args(argv)
    panels = []
    with tempfile.TemporaryDirectory() as tmp:
        for mode in MODES:
            image = render_mode(mode, args.frame, Path(tmp) / mode)
            text = {"raster": "raster", "hybrid": "hybrid (HEU1)", "rt": "rt (reference)"}[mode]
            panels.append(np.vstack([image, label(text, image.shape[1])]))
    height = panels[0].shape[0]
    gap = np.full((height, GAP, 3), 255, np.uint8)
    strip = np.hstack([p if i == 0 else np.hstack([gap, p]) for i, p in enumerate(panels)])
    write_png_atomic(args.out, strip)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
