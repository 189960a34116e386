"""Our renders against Mitsuba 3's on small stages of UsdPreviewSurface spheres on a floor
(``phrt_usd/bench/mitsuba_comparison.py`` says what the stages are, where the two
renderers are meant to agree and what they do not share).

    uv run python tools/compare_mitsuba.py [STAGE ...] [--resolution 96x72] [--spp 2025]
        [--images DIR] [--json]

Each stage (default: all of ``STAGES``) is rendered in ``rt``, ``hybrid`` (every
reflector traced, no budget) and Mitsuba (the optional ``bench`` extra, ``scalar_rgb``);
reported per stage: the mean FLIP of rt and of hybrid against Mitsuba, and of hybrid
against rt. ``--images DIR`` writes the three renders of each stage as PNGs and the FLIP
map of rt against Mitsuba. Exit 2 for an unknown stage, a bad resolution or spp, or
Mitsuba not installed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from phrt_usd.api import parse_resolution
from phrt_usd.bench import mitsuba_comparison
from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.image_metrics import flip_map
from phrt_usd.run.images import write_preview_png


def stage_errors(images: mitsuba_comparison.StageImages) -> dict:
    """Mean FLIP of rt and hybrid against Mitsuba, and of hybrid against rt."""
    return {
        "stage": images.name,
        "rt_vs_mitsuba": float(flip_map(images.mitsuba, images.rt).mean()),
        "hybrid_vs_mitsuba": float(flip_map(images.mitsuba, images.hybrid).mean()),
        "hybrid_vs_rt": float(flip_map(images.rt, images.hybrid).mean()),
    }


def write_images(images: mitsuba_comparison.StageImages, directory: Path) -> None:
    """The three renders and the FLIP map of rt against Mitsuba, as PNGs."""
    directory.mkdir(parents=True, exist_ok=True)
    for kind in ("rt", "hybrid", "mitsuba"):
        write_preview_png(directory / f"{images.name}_{kind}.png", getattr(images, kind))
    error = flip_map(images.mitsuba, images.rt)
    write_preview_png(directory / f"{images.name}_flip_rt.png", np.repeat(error[..., None], 3, 2))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stages", nargs="*", help=f"of {', '.join(mitsuba_comparison.STAGES)}")
    parser.add_argument("--resolution", default="96x72")
    parser.add_argument("--spp", type=int, default=mitsuba_comparison.DEFAULT_SPP)
    parser.add_argument("--images", type=Path, default=None)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    try:
        width, height = parse_resolution(args.resolution)
        if width < 2 or height < 2:  # FLIP needs 2 x 2 pixels
            raise PhrtError(f"--resolution {args.resolution}: at least 2x2")
        if args.spp < 1:
            raise PhrtError(f"--spp {args.spp}: at least 1")
        names = args.stages or list(mitsuba_comparison.STAGES)
        for name in names:
            mitsuba_comparison.comparison_stage(name, width, height)  # refuses unknown names
        rows = []
        for name in names:
            images = mitsuba_comparison.render_stage(name, width, height, args.spp)
            if args.images is not None:
                write_images(images, args.images)
            rows.append(stage_errors(images))
            if not args.json:
                row = rows[-1]
                print(f"{name:10s} rt {row['rt_vs_mitsuba']:.4f}  "
                      f"hybrid {row['hybrid_vs_mitsuba']:.4f}  "
                      f"hybrid-rt {row['hybrid_vs_rt']:.4f}")  # fmt: skip
    except PhrtError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"resolution": [width, height], "spp": args.spp, "stages": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
