"""Before/after check for refactors: render fixed frames of both paper stages in every mode
with a rays budget (deterministic), then compare two such sets channel by channel.

    uv run python tools/compare_renders.py render runs/before
    ... change the code ...
    uv run python tools/compare_renders.py render runs/after
    uv run python tools/compare_renders.py compare runs/before runs/after

``render`` writes ``DIR/<stage>_<mode>/`` (a normal ``phrt render`` run directory) for
each stage and mode. ``compare`` reads every EXR of the first set and its namesake in the
second and prints, per run, the number of frames and of pixels that differ in any channel
(R, G, B, A, Z, id, traced, and any other channel present in both); it exits 1 if any
pixel differs or a frame is missing, 0 if every channel of every frame is identical.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

ROOT = Path(__file__).resolve().parent.parent
#: Stage, frames (where reflectors are in view) and the rays budget per frame: a budget
#: that selects some reflectors but not all, so the heuristics' choices show.
RUNS = (
    ("farm", ROOT / "stages" / "farm.usda", "521:540", 1000),
    ("sewer", ROOT / "stages" / "sewer.usda", "1:20", 10000),
)
MODES = ("raster", "hybrid", "rt")
RESOLUTION = "320x240"


def render(folder: Path) -> None:
    for name, stage, frames, rays in RUNS:
        for mode in MODES:
            out = folder / f"{name}_{mode}"
            cmd = [sys.executable, "-m", "typer", "phrt_usd.cli",
                   "run", "render", str(stage), "--out", str(out), "--overwrite",
                   "--frames", frames, "--mode", mode, "--budget-rays", str(rays),
                   "--resolution", RESOLUTION, "--json"]  # fmt: skip
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                sys.exit(f"{name} {mode}: render failed: {done.stderr.strip()[-500:]}")
            print(f"{name} {mode}: {out}", file=sys.stderr)


def _channels(path: Path) -> dict[str, np.ndarray]:
    image = oiio.ImageInput.open(str(path))
    if image is None:
        sys.exit(f"{path}: cannot open ({oiio.geterror()})")
    try:
        spec = image.spec()
        out = {}
        for i, name in enumerate(spec.channelnames):
            # Integer channels read as integers (OIIO would normalise them to [0, 1]).
            kind = spec.channelformat(i)
            fmt = oiio.UINT if kind.basetype == oiio.UINT else oiio.FLOAT
            out[name] = image.read_image(0, 0, i, i + 1, fmt)[..., 0]
    finally:
        image.close()
    return out


def _ids(channel: np.ndarray) -> np.ndarray:
    """Element ids as int64 whatever the channel's storage; background is -1."""
    ids = np.rint(channel.astype(np.float64)).astype(np.int64)
    ids[ids == 2**32 - 1] = -1
    return ids


def compare(before: Path, after: Path) -> int:
    failed = False
    for run in sorted(p for p in before.iterdir() if p.is_dir()):
        frames = sorted((run / "frames").glob("*.exr"))
        differing_frames = differing_pixels = 0
        for exr in frames:
            other = after / run.name / "frames" / exr.name
            if not other.exists():
                print(f"{run.name}: {exr.name} missing after")
                failed = True
                continue
            a, b = _channels(exr), _channels(other)
            if set(a) != set(b):
                print(f"{run.name}/{exr.name}: channels {sorted(a)} vs {sorted(b)}")
            differ = np.zeros(next(iter(a.values())).shape, dtype=bool)
            for name in set(a) & set(b):
                if name == "id":  # stored as float or as uint (background -1 or 2**32-1)
                    differ |= _ids(a[name]) != _ids(b[name])
                    continue
                # Bit-identical, NaN == NaN: the refactor must not change a single value.
                differ |= a[name].view(np.uint32) != b[name].view(np.uint32)
            if differ.any():
                differing_frames += 1
                differing_pixels += int(differ.sum())
        failed |= differing_frames > 0 or not frames
        print(f"{run.name}: {len(frames)} frames, {differing_frames} differ "
              f"({differing_pixels} pixels)")  # fmt: skip
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    sub.add_parser("render").add_argument("folder", type=Path)
    cmp = sub.add_parser("compare")
    cmp.add_argument("before", type=Path)
    cmp.add_argument("after", type=Path)
    args = ap.parse_args(argv)
    if args.command == "render":
        render(args.folder)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    raise SystemExit(main())
