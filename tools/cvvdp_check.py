"""Does our temporal error rank configurations as ColorVideoVDP does?

Compares, over the same rendered frames, the project's per-frame FLIP and temporal error
(``phrt_usd.evaluate.image_metrics``, docs/temporal-error.md) with ColorVideoVDP
(``cvvdp``, Mantiuk et al. 2024), the calibrated video-difference metric, and prints a
markdown table and the Spearman rank correlations. cvvdp needs torch, which is not a
dependency of phrt-usd, so the check runs in two steps under two Python environments:

1. ``ours`` (the project's environment): reads the ``phrt render`` output directories
   (``DIR/frames/*.exr`` and ``DIR/stats.json``) of a reference (``--heuristic all``,
   rendered with ``--aovs motion``: the warp reads its motion vectors, depth and ids,
   which every configuration of the same frames shares) and of each configuration,
   computes per frame FLIP and the temporal error against the reference with the
   project's own functions, counts transitions, and writes a JSON::

       uv run python tools/cvvdp_check.py ours /tmp/cv/all /tmp/cv/none /tmp/cv/heu1-10000 \\
           ... --out /tmp/cv/ours.json

2. ``cvvdp`` (a separate venv holding torch and cvvdp, never the project's .venv): reads
   that JSON and the same directories' ``frames/*.png`` previews, scores each
   configuration's sequence against the reference's with cvvdp and prints the table::

       /tmp/cvvdp-venv/bin/python tools/cvvdp_check.py cvvdp /tmp/cv/ours.json

Why the PNG previews for cvvdp: they are ``images.tonemap_ldr`` of the beauty (clamp to
[0, 1], sRGB encoding) in 8 bits, i.e. display-referred SDR frames, the very images our
FLIP and temporal error judge (they tone-map with ``tonemap_ldr`` first). cvvdp is
therefore given an SDR display model with the sRGB EOTF (``standard_4k``'s photometry:
200 cd/m² peak, contrast 1000:1, 250 lux office light) and display-encoded input in
[0, 1]. An HDR model (PQ, absolute luminance) would judge linear radiance above 1 that the
previews and our metrics clamp away. The display geometry is a fixed ``PIXELS_PER_DEGREE``
so that cvvdp views the frames under FLIP's viewing condition. The frame rate given to
cvvdp is the recorded sequence's
(``temporal_error.sequence_frames_per_second`` of the reference's stats.json: the stage's
``timeCodesPerSecond`` for consecutive time codes), as the sweep takes it.

Spearman's rho is taken between our error and ``-JOD`` (JOD is higher-better, our errors
lower-better), so rho = +1 means the same ranking.

Our temporal error here is the sweep's (``temporal_error``: the warped-frame error beyond
the reference's, per pixel), with one difference: the files hold no depth of a pixel's
point in the previous camera, so the warp masks by element id alone
(``FrameWarp.between`` without ``expected_depth``).
"""

from __future__ import annotations

import argparse
import json
import sys
import types
from pathlib import Path

import numpy as np

#: FLIP's default viewing condition (LDR-FLIP at 67 pixels per degree, image_metrics), used
#: as cvvdp's display geometry so both metrics see the frames at the same angular size.
PIXELS_PER_DEGREE = 67.0
#: cvvdp's SDR display model whose photometry (sRGB EOTF, 200 cd/m², 1000:1, 250 lux) is used.
DISPLAY_PHOTOMETRY = "standard_4k"
#: torchvision modules that register fake kernels of its C ops (nms, roi_align...) at import;
#: they fail when torchvision's compiled ops were built for another torch (PyPI's torchvision
#: wheel is linked against CUDA torch; ours is the CPU build). cvvdp uses only torchvision's
#: pure-torch GaussianBlur, so these registrations are skipped when the plain import fails.
TORCHVISION_OP_REGISTRATIONS = ("torchvision._meta_registrations",
                                "torchvision._autograd_registrations")


def fail(message: str) -> None:
    """Exit with one line on stderr (exit code 2)."""
    print(f"cvvdp_check: {message}", file=sys.stderr)
    raise SystemExit(2)


def spearman(a: list[float], b: list[float]) -> float | None:
    """Spearman's rank correlation of two equal-length samples (average ranks for ties);
    None when it is undefined (fewer than 3 values, or one sample constant)."""
    x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if x.shape != y.shape or x.size < 3:
        return None
    rx, ry = _average_ranks(x), _average_ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    norm = float(np.sqrt((rx * rx).sum() * (ry * ry).sum()))
    return None if norm == 0.0 else float((rx * ry).sum() / norm)


def _average_ranks(values: np.ndarray) -> np.ndarray:
    """(N,) float64 ranks 1..N of (N,) values, tied values sharing their mean rank."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(values.size, dtype=np.float64)
    ranks[order] = np.arange(1, values.size + 1, dtype=np.float64)
    uniques, inverse = np.unique(values, return_inverse=True)
    sums = np.bincount(inverse, weights=ranks, minlength=uniques.size)
    counts = np.bincount(inverse, minlength=uniques.size)
    return (sums / counts)[inverse]


def frame_names(directory: Path, suffix: str) -> list[str]:
    """Sorted file names ``frames/*.<suffix>`` of a ``phrt render`` output directory."""
    names = sorted(p.name for p in (directory / "frames").glob(f"*.{suffix}"))
    if not names:
        fail(f"{directory}/frames: no *.{suffix} frames (a `phrt render` output directory?)")
    return names


def _check_same_frames(reference: Path, directory: Path, suffix: str) -> list[str]:
    names = frame_names(reference, suffix)
    if frame_names(directory, suffix) != names:
        fail(f"{directory}: its frames/*.{suffix} are not the reference's {reference} frames")
    return names


# --- step 1: our metrics (project environment) ------------------------------------------


def our_metrics(reference: Path, directory: Path, frames_per_second: float) -> dict:
    """Per-configuration figures of ``directory`` against ``reference`` (render outputs of
    a sequence at ``frames_per_second``): mean per-frame FLIP, mean temporal error (over
    every frame but the first), transitions, mean frame ms and rays per frame (from
    stats.json)."""
    from phrt_usd.evaluate.image_metrics import flip_map, mean_over
    from phrt_usd.evaluate.selection_metrics import selection_metrics
    from phrt_usd.evaluate.temporal_error import WarpedSequence, popping_map
    from phrt_usd.run.images import read_frame_exr

    names = _check_same_frames(reference, directory, "exr")
    flips, temporals = [], []
    ref_sequence, test_sequence = WarpedSequence(), WarpedSequence()
    for name, warp in zip(names, reference_warps(reference, names), strict=True):
        ref = read_frame_exr(reference / "frames" / name)["beauty"]
        test = read_frame_exr(directory / "frames" / name)["beauty"]
        flips.append(mean_over(flip_map(ref, test)))
        ref_warped, test_warped = ref_sequence.push(ref, warp), test_sequence.push(test, warp)
        if warp is not None:
            temporals.append(mean_over(popping_map(test_warped, ref_warped), warp.valid))
    stats = json.loads((directory / "stats.json").read_text())
    frames = stats["frames"]
    reflectors = stats["run"]["reflectors"]
    column = {path: i for i, path in enumerate(reflectors)}
    selected = np.zeros((len(frames), len(reflectors)), dtype=bool)
    visible = np.zeros_like(selected)
    for f, frame in enumerate(frames):
        visible[f, [column[p] for p in frame["visible"]]] = True
        selected[f, [column[p] for p in frame["selected"]]] = True
    run = stats["run"]
    return {
        "label": directory.name,
        "directory": str(directory),
        "heuristic": run["heuristic"],
        "budget_rays": run["budget_rays"],
        "budget_ms": run["budget_ms"] if run["budget_rays"] is None else None,
        "frames": len(names),
        "flip": float(np.mean(flips)),
        "temporal_error": float(np.mean(temporals)) if temporals else 0.0,
        "transitions": selection_metrics(selected, visible)["transitions"],
        "frame_ms": float(np.mean([fr["frame_ms"] for fr in frames])),
        "rays": float(np.mean([fr["rays"] for fr in frames])),
    }


def reference_warps(reference: Path, names: list[str]) -> list:
    """Each frame's ``FrameWarp`` from the previous one (None for the first), from the
    reference's ``motion.x`` / ``motion.y``, ``Z`` and ``id`` channels; one line and exit
    2 when its frames hold no motion (render it with ``--aovs motion``)."""
    from phrt_usd.evaluate.temporal_error import FrameWarp
    from phrt_usd.run.images import element_ids, read_exr

    warps, previous = [], None
    for name in names:
        _, channels = read_exr(reference / "frames" / name)
        if "motion.x" not in channels or "motion.y" not in channels:
            fail(f"{reference}/frames/{name}: no motion.x / motion.y channels; render the "
                 "reference with --aovs motion")
        motion = np.stack([channels["motion.x"], channels["motion.y"]], -1).astype(np.float32)
        ids = element_ids(channels["id"])
        depth = channels["Z"].astype(np.float32)
        warps.append(None if previous is None else
                     FrameWarp.between(motion, ids, previous[0], previous[1]))
        previous = (ids, depth)
    return warps


def run_ours(args: argparse.Namespace) -> None:
    from phrt_usd.evaluate.temporal_error import sequence_frames_per_second

    reference = Path(args.reference)
    stats = json.loads((reference / "stats.json").read_text())
    run = stats["run"]
    if run["heuristic"] != "all":
        fail(f"{reference}: the reference must be rendered with --heuristic all")
    configs = []
    # The recorded sequence's rate, as the sweep takes it (every 2nd time code: half).
    fps = sequence_frames_per_second(
        [frame["time"] for frame in stats["frames"]], run["time_codes_per_second"]
    )
    for directory in args.configs:
        configs.append(our_metrics(reference, Path(directory), fps))
        print(f"{configs[-1]['label']}: FLIP {configs[-1]['flip']:.4f} temporal "
              f"{configs[-1]['temporal_error']:.4f}", file=sys.stderr)
    result = {
        "reference": str(reference),
        "stage": run["stage"],
        "frame_range": run["frame_range"],
        "resolution": run["resolution"],
        "frames_per_second": fps,
        "configs": configs,
    }
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}", file=sys.stderr)


def run_alternate(args: argparse.Namespace) -> None:
    """Write a synthetic configuration that pops on purpose: frames taken alternately
    ``period`` at a time from two render outputs A and B (A first), with a stats.json
    whose per-frame entries (selection, timings) are those of the frames' sources, so
    ``ours`` counts its transitions. The popping control of docs/temporal-error.md.

    With ``--blend``, its steady counterpart instead: every frame is the mean of A's and
    B's linear beauty (no switch, about the same per-frame error as alternating), with
    B's per-frame stats (the project's env: it writes EXR and PNG with phrt_usd)."""
    import shutil

    first, second, out = Path(args.first), Path(args.second), Path(args.out)
    names = _check_same_frames(first, second, "exr")
    _check_same_frames(first, second, "png")
    stats = [json.loads((d / "stats.json").read_text()) for d in (first, second)]
    if len(stats[0]["frames"]) != len(names) or len(stats[1]["frames"]) != len(names):
        fail(f"{first} and {second}: stats.json frames do not match frames/*.exr")
    (out / "frames").mkdir(parents=True, exist_ok=True)
    frames = []
    label = f"blend {first.name}/{second.name}" if args.blend else (
        f"alternate {first.name}/{second.name} every {args.period}")
    if args.blend:
        _write_blend(first, second, out, names)
        frames = stats[1]["frames"]
    for index, name in enumerate([] if args.blend else names):
        source = (index // args.period) % 2
        directory = (first, second)[source]
        for suffix in ("exr", "png"):
            stem = name.removesuffix(".exr")
            shutil.copyfile(directory / "frames" / f"{stem}.{suffix}",
                            out / "frames" / f"{stem}.{suffix}")
        frames.append(stats[source]["frames"][index])
    run = dict(stats[1]["run"])
    run["heuristic"] = label
    run["budget_rays"] = None
    run["budget_ms"] = None
    (out / "stats.json").write_text(json.dumps({"run": run, "frames": frames}, indent=1))
    print(f"wrote {out}", file=sys.stderr)


def _write_blend(first: Path, second: Path, out: Path, names: list[str]) -> None:
    """frames/<name>.exr and .png under ``out``: the mean of A's and B's linear beauty
    (other channels, motion included: A's)."""
    from phrt_usd.run.images import read_frame_exr, write_preview_png

    for name in names:
        a = read_frame_exr(first / "frames" / name)
        b = read_frame_exr(second / "frames" / name)
        beauty = np.float32(0.5) * (a["beauty"] + b["beauty"])
        stem = name.removesuffix(".exr")
        write_frame(out / "frames" / f"{stem}.exr", beauty, a["element_id"],
                    _motion_of(first / "frames" / name), a["depth"])
        write_preview_png(out / "frames" / f"{stem}.png", beauty)


def _motion_of(path: Path) -> np.ndarray | None:
    """(H, W, 2) the motion channels of an EXR, None without them."""
    from phrt_usd.run.images import read_exr

    _, channels = read_exr(path)
    if "motion.x" not in channels:
        return None
    return np.stack([channels["motion.x"], channels["motion.y"]], -1).astype(np.float32)


def write_frame(path: Path, beauty: np.ndarray, ids: np.ndarray, motion: np.ndarray | None,
                depth: np.ndarray | None = None) -> None:
    """A frame in the default layout (``images.write_frame_exr``'s channels: coverage and
    traced from ``ids``, depth 2 m unless given) plus ``motion.x`` / ``motion.y`` (float)
    when ``motion`` (H, W, 2) is given, as ``phrt render --aovs motion`` writes them."""
    from phrt_usd.run.images import stored, stored_depth, stored_ids, write_exr

    covered = (ids >= 0).astype(np.float32)
    depth = np.full(ids.shape, 2.0, np.float32) if depth is None else depth
    channels = {"R": stored(beauty[..., 0], "half"), "G": stored(beauty[..., 1], "half"),
                "B": stored(beauty[..., 2], "half"), "A": stored(np.ones(ids.shape), "half"),
                "Z": stored_depth(path, depth), "id": stored_ids(path, ids),
                "traced": stored(covered, "half")}
    if motion is not None:
        channels["motion.x"] = stored(motion[..., 0], "float")
        channels["motion.y"] = stored(motion[..., 1], "float")
    write_exr(path, {"": channels})


#: The synthetic sequences of ``synthetic`` (docs/temporal-error.md, "Synthetic
#: sequences"): 320x240, 24 frames at 24 fps, a sine background (still or shifting 0.7 rad
#: a frame: SYNTHETIC_PERIOD_PX x 0.7 / 2 pi = 21 pixels left), a patch of +PATCH linear
#: radiance on its middle quarter (still on screen).
SYNTHETIC_SIZE = (320, 240)
SYNTHETIC_WAVELENGTH_PX = 30.0  # the background's sin(x / 30 + phase)
SYNTHETIC_PHASE_STEP = 0.7
SYNTHETIC_FRAMES = 24
SYNTHETIC_PATCH = 0.3


def run_synthetic(args: argparse.Namespace) -> None:
    """Write render-like outputs (frames/*.exr, *.png, stats.json) of synthetic sequences
    under ``--out``: the background alone (``reference``, as if rendered with ``all``),
    the patch in every frame (``steady``), half the patch in every frame (``blend``), and
    the patch switched on and off every 1, 2 and 4 frames (``pop1`` 12 Hz, ``pop2`` 6 Hz,
    ``pop4`` 3 Hz); ``--moving`` shifts the background every frame. The frames carry
    their exact motion: the background's shift, 0 on the patch."""
    from phrt_usd.run.images import write_preview_png

    width, height = SYNTHETIC_SIZE
    x = np.arange(width, dtype=np.float32)
    patch = (slice(height // 4, 3 * height // 4), slice(width // 4, 3 * width // 4))
    amounts = {"reference": lambda t: 0.0, "steady": lambda t: SYNTHETIC_PATCH,
               "blend": lambda t: SYNTHETIC_PATCH / 2}
    for period in (1, 2, 4):
        amounts[f"pop{period}"] = (
            lambda t, p=period: SYNTHETIC_PATCH if (t // p) % 2 else 0.0)
    ids = np.full((height, width), -1, dtype=np.int32)
    ids[patch] = 0
    # sin(x / L + s t): what is at x now was at x + L s a frame before (motion -L s).
    motion = np.zeros((height, width, 2), np.float32)
    if args.moving:
        motion[ids < 0, 0] = -SYNTHETIC_WAVELENGTH_PX * SYNTHETIC_PHASE_STEP
    for name, amount in amounts.items():
        out = Path(args.out) / name
        (out / "frames").mkdir(parents=True, exist_ok=True)
        frames = []
        for t in range(SYNTHETIC_FRAMES):
            phase = SYNTHETIC_PHASE_STEP * t if args.moving else 0.0
            row = 0.25 + 0.15 * np.sin(x / SYNTHETIC_WAVELENGTH_PX + phase)
            beauty = np.repeat(np.repeat(row[None, :, None], height, 0), 3, 2)
            beauty[patch] += amount(t)
            stem = f"{1 + t:04d}"
            write_frame(out / "frames" / f"{stem}.exr", beauty, ids, motion)
            write_preview_png(out / "frames" / f"{stem}.png", beauty)
            frames.append({"time": float(1 + t), "frame_ms": 0.0, "rays": 0,
                           "visible": ["/Patch"],
                           "selected": ["/Patch"] if amount(t) == 0.0 else []})
        run = {"stage": "synthetic", "heuristic": "all" if name == "reference" else name,
               "budget_ms": None, "budget_rays": None, "resolution": [width, height],
               "frame_range": [1.0, float(SYNTHETIC_FRAMES)], "time_codes_per_second": 24.0,
               "reflectors": ["/Patch"]}
        (out / "stats.json").write_text(json.dumps({"run": run, "frames": frames}, indent=1))
    print(f"wrote {args.out}", file=sys.stderr)


# --- step 2: cvvdp (separate venv) --------------------------------------------------------


def import_cvvdp() -> types.ModuleType:
    """pycvvdp, importing torchvision without its C-op registrations if the plain import
    fails (see ``TORCHVISION_OP_REGISTRATIONS``); one line and exit 2 if not importable."""
    hint = "run this step under a separate venv with torch (CPU) and cvvdp, docs/temporal-error.md"
    try:
        import torch  # noqa: F401
    except Exception as exc:  # ImportError, or a torch that fails to load
        fail(f"cannot import torch for cvvdp ({type(exc).__name__}: {exc}); {hint}")
    try:
        import torchvision  # noqa: F401
    except ModuleNotFoundError:
        pass  # the pycvvdp import below fails and says so
    except Exception:  # RuntimeError from the op registrations: retry without them
        for name in [n for n in sys.modules if n.split(".")[0] == "torchvision"]:
            del sys.modules[name]
        for name in TORCHVISION_OP_REGISTRATIONS:
            sys.modules[name] = types.ModuleType(name)
        print("cvvdp_check: torchvision's C ops do not load with this torch; importing it "
              "without them (cvvdp uses only its GaussianBlur)", file=sys.stderr)
    try:
        import pycvvdp
    except Exception as exc:  # ImportError, or torchvision failing to load
        fail(f"cannot import cvvdp ({type(exc).__name__}: {exc}); {hint}")
    return pycvvdp


def load_png_sequence(directory: Path, names: list[str]) -> np.ndarray:
    """(F, H, W, 3) float32 display-encoded sRGB in [0, 1] of ``frames/<name>`` PNGs."""
    from PIL import Image

    return np.stack([
        np.asarray(Image.open(directory / "frames" / name).convert("RGB"), dtype=np.float32)
        / np.float32(255.0)
        for name in names
    ])


def run_cvvdp(args: argparse.Namespace) -> None:
    pycvvdp = import_cvvdp()
    import torch

    ours = json.loads(Path(args.ours).read_text())
    reference = Path(ours["reference"])
    fps = float(ours["frames_per_second"])
    width, height = ours["resolution"]
    photometry = pycvvdp.vvdp_display_photometry.load(DISPLAY_PHOTOMETRY, [])
    geometry = pycvvdp.vvdp_display_geometry((width, height), ppd=args.ppd)
    metric = pycvvdp.cvvdp(display_photometry=photometry, display_geometry=geometry,
                           quiet=True, device=torch.device("cpu"))
    names = frame_names(reference, "png")
    ref = torch.from_numpy(load_png_sequence(reference, names))
    for config in ours["configs"]:
        directory = Path(config["directory"])
        _check_same_frames(reference, directory, "png")
        test = torch.from_numpy(load_png_sequence(directory, names))
        with torch.no_grad():
            jod, _stats = metric.predict(test, ref, dim_order="FHWC", frames_per_second=fps)
        config["cvvdp_jod"] = float(jod)
        print(f"{config['label']}: JOD {config['cvvdp_jod']:.3f}", file=sys.stderr)
    print_table(ours, args.ppd, pycvvdp, torch)


def print_table(ours: dict, ppd: float, pycvvdp: types.ModuleType, torch: types.ModuleType):
    """The markdown table and the rank correlations, on stdout."""
    from importlib.metadata import version

    configs = ours["configs"]
    first, last = ours["frame_range"]
    print(f"{ours['stage']}, frames {first:g}-{last:g}, {ours['resolution'][0]}x"
          f"{ours['resolution'][1]}, reference `{ours['reference']}`; cvvdp "
          f"{version('cvvdp')} (torch {torch.__version__}), display '{DISPLAY_PHOTOMETRY}' "
          f"photometry (SDR, sRGB EOTF) at {ppd:g} pixels per degree, "
          f"{ours['frames_per_second']:g} frames per second\n")
    print("| configuration | frame ms | rays/frame | transitions | per-frame FLIP "
          "| temporal error | cvvdp JOD |")
    print("|---|---|---|---|---|---|---|")
    for c in sorted(configs, key=lambda c: c["cvvdp_jod"]):
        print(f"| {c['label']} | {c['frame_ms']:.0f} | {c['rays']:.0f} | {c['transitions']} "
              f"| {c['flip']:.4f} | {c['temporal_error']:.4f} | {c['cvvdp_jod']:.3f} |")
    minus_jod = [-c["cvvdp_jod"] for c in configs]
    for name, key in (("temporal error", "temporal_error"), ("per-frame FLIP", "flip"),
                      ("transitions", "transitions")):
        rho = spearman([c[key] for c in configs], minus_jod)
        shown = "undefined" if rho is None else f"{rho:+.3f}"
        print(f"\nSpearman rho({name}, -JOD) over {len(configs)} configurations: {shown}")
    rho = spearman([c["temporal_error"] for c in configs], [c["flip"] for c in configs])
    shown = "undefined" if rho is None else f"{rho:+.3f}"
    print(f"\nSpearman rho(temporal error, per-frame FLIP): {shown}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="step", required=True)
    ours = sub.add_parser("ours", help="our metrics of render outputs (project env)")
    ours.add_argument("reference", help="`phrt render --heuristic all` output directory")
    ours.add_argument("configs", nargs="+", help="configurations' render output directories")
    ours.add_argument("--out", required=True, help="JSON written for the cvvdp step")
    cv = sub.add_parser("cvvdp", help="cvvdp of the same sequences, and the table (cvvdp venv)")
    cv.add_argument("ours", help="JSON of the `ours` step")
    cv.add_argument("--ppd", type=float, default=PIXELS_PER_DEGREE,
                    help=f"pixels per degree of cvvdp's display (default {PIXELS_PER_DEGREE:g})")
    alt = sub.add_parser("alternate", help="a popping control: frames of A and B in turn")
    alt.add_argument("first", help="render output A (e.g. the `all` reference)")
    alt.add_argument("second", help="render output B (e.g. raster-only `none`)")
    alt.add_argument("--period", type=int, default=1, help="frames taken from each in turn")
    alt.add_argument("--blend", action="store_true",
                     help="every frame the mean of A and B instead (the steady counterpart)")
    alt.add_argument("--out", required=True, help="output directory")
    syn = sub.add_parser("synthetic", help="synthetic steady, blended and popping sequences")
    syn.add_argument("--moving", action="store_true", help="shift the background every frame")
    syn.add_argument("--out", required=True, help="output directory")
    args = parser.parse_args(argv)
    if args.step == "alternate" and args.period < 1:
        fail(f"--period must be >= 1, got {args.period}")
    steps = {"ours": run_ours, "cvvdp": run_cvvdp, "alternate": run_alternate,
             "synthetic": run_synthetic}
    steps[args.step](args)


if __name__ == "__main__":
    main()
