"""The picture of docs/pixel-kinds.md: one frame of the sewer and beside it how each of
its pixels was made (the ``phrt:pixelKind`` RenderVar, ``phrt_usd/model/pixel_kinds.py``),
as a debug view.

    uv run python tools/pixel_kinds_picture.py [--frame 241] [--out docs/pixel-kinds.png]

Renders the frame with ``phrt render --aovs pixelKind,reflectivity`` (HEU1 at a rays
budget, so the selection is the same on every machine, at a quarter trace density, so
the filled pixels show) into a temporary directory, then draws the preview and the kinds
side by side with a legend counting each kind's pixels. In the kinds view a reflector's
pixels take their kind's colour; pixels of other surfaces (raster, no reflection) show
the frame's own luminance, dimmed, so the scene stays readable.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from phrt_usd.atomic import atomic_path
from phrt_usd.model import pixel_kinds as pk
from phrt_usd.run.images import read_exr, read_preview_png

ROOT = Path(__file__).resolve().parent.parent
STAGE = ROOT / "stages" / "sewer.usda"
RESOLUTION = "320x240"
#: HEU1 within this many rays a frame, every reflector of 64+ pixels traced at a quarter of
#: its pixels: some reflectors traced (traced and filled pixels), the others raster.
BUDGET_RAYS = 30000
DENSITY = "quarter"
#: Colour (sRGB in [0, 1]) of each kind on a reflector; off reflectors "raster" is grey.
KIND_COLOURS = {
    pk.BACKGROUND: (0.0, 0.0, 0.0),
    pk.RASTER: (0.95, 0.6, 0.1),  # a reflector left at its raster fallback
    pk.SCREEN_SPACE: (0.2, 0.85, 0.95),
    pk.TRACED: (0.2, 0.8, 0.2),
    pk.REUSED: (0.85, 0.3, 0.85),
    pk.FILLED: (0.25, 0.45, 1.0),
}
#: Brightness of the non-reflector pixels' luminance in the kinds view.
DIM = 0.45
FIGURE_DPI = 100


def render(frame: float, out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(preview (H, W, 3) uint8, kinds (H, W) uint8, reflectivity (H, W)) of ``frame``."""
    cmd = [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "-q", "render", str(STAGE),
           "--out", str(out), "--frames", f"{frame:g}", "--resolution", RESOLUTION,
           "--heuristic", "heu1", "--budget-ms", "inf", "--budget-rays", str(BUDGET_RAYS),
           "--trace-density", DENSITY, "--aovs", "pixelKind,reflectivity", "--json"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"render: {done.stderr.strip()}")
    exr = next((out / "frames").glob("*.exr"))
    _, channels = read_exr(exr)
    preview = read_preview_png(exr.with_suffix(".png"))
    return preview, channels["pixelKind"].astype(np.uint8), channels["reflectivity"]


def kind_view(preview: np.ndarray, kinds: np.ndarray, reflectivity: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1]: each reflector pixel in its kind's colour, other
    surfaces in their dimmed luminance, background black."""
    grey = DIM * (preview.astype(np.float32) / 255.0) @ np.array([0.2126, 0.7152, 0.0722])
    view = np.repeat(grey[..., None], 3, axis=2)
    reflector = np.asarray(reflectivity) > 0.0
    for code, colour in KIND_COLOURS.items():
        where = (kinds == code) & (reflector | (code == pk.BACKGROUND))
        view[where] = colour
    return view


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frame", type=float, default=241.0, help="time code (wet tunnel)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "pixel-kinds.png")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        preview, kinds, reflectivity = render(args.frame, Path(tmp))
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt
    from matplotlib.patches import Patch

    height, width = kinds.shape
    counts = pk.kind_counts(kinds)
    reflector = reflectivity > 0.0
    fig, axes = plt.subplots(1, 2, figsize=(2 * width / FIGURE_DPI, (height + 70) / FIGURE_DPI),
                             dpi=FIGURE_DPI)  # fmt: skip
    fig.subplots_adjust(left=0.005, right=0.995, top=0.92, bottom=0.22, wspace=0.02)
    axes[0].imshow(preview, interpolation="nearest")
    axes[0].set_title(f"sewer frame {args.frame:g}, HEU1 {BUDGET_RAYS} rays, {DENSITY}",
                      fontsize=8)  # fmt: skip
    axes[1].imshow(kind_view(preview, kinds, reflectivity), interpolation="nearest")
    axes[1].set_title("how each pixel was made (reflectors in colour)", fontsize=8)
    for ax in axes:
        ax.set_axis_off()
    fallback = int(((kinds == pk.RASTER) & reflector).sum())
    entries = [
        (pk.RASTER, f"raster fallback ({fallback} px)"),
        (pk.TRACED, f"traced ({counts['traced']})"),
        (pk.FILLED, f"filled ({counts['filled']})"),
        (pk.SCREEN_SPACE, f"screen-space ({counts['screen-space']})"),
        (pk.REUSED, f"reused ({counts['reused']})"),
    ]
    handles = [Patch(color=KIND_COLOURS[c], label=text) for c, text in entries]
    handles.append(Patch(color=(DIM, DIM, DIM), label="other surfaces: raster (grey)"))
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=7, frameon=False)
    out = Path(args.out)
    with atomic_path(out) as path:
        fig.savefig(path, format="png", dpi=FIGURE_DPI, metadata={"Software": None})
    plt.close(fig)
    print(f"wrote {out}: {counts}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
