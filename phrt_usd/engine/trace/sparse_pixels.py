"""Tracing large reflectors at reduced density: which of their pixels start rays, and how
the others get their reflection from traced samples (``--trace-density``, HEU1's
density steps).

The pixels of a reflector with at least its density's ``sparse_floor`` of pixels in a
frame (``model/trace_density.py``) are traced on a pattern: at a density of k/16, the
pixels of each 4 x 4 block whose ordered-dither rank (BAYER_RANKS) is below k. Its
regular patterns: ``half`` a checkerboard (row + column even), ``quarter`` one pixel of
each 2 x 2 block (row and column even), ``eighth`` the checkerboard of those,
``sixteenth`` one of each 4 x 4 block (row and column multiples of 4); a density between
two of them traces the coarser one's pixels and the next ranks. A ``phase`` (row,
column) shifts the pattern (a pattern rotating from frame to frame passes the frame's).
Smaller reflectors are traced whole: their savings are small and their edges are most
of their pixels.

The other pixels are reconstructed (``fill_skipped``, compiled in ``fill_kernels``, whose
docstring has the rule and its constants): an edge-aware Catmull-Rom interpolation on
the lattice of the density's regular pattern (the cell's four traced corners and the 8
lattice points that extend them), each traced sample weighed by how far it belongs with the pixel:

- its reflector: only the pixel's own (never across reflectors);
- the G-buffer's normals (n . n')^256: a crease stops the fill, and on a rippled
  (normal-mapped) reflector the samples whose normal matches the pixel's, which reflect
  what it does, count most;
- the G-buffer's positions: a sample off the pixel's tangent plane (a depth step, a
  fold of the same mesh) counts for nothing;
- the reflection's hit distance (how far the traced ray went): a sample whose
  reflected surface is much nearer or farther than the pixel's estimate (the
  reflection of a near object over a far one) counts little, so the pixel takes one
  side of the reflected edge.

Traced pixels keep their traced values exactly; a filled one stays within the range of
the cell corners it used (no ringing, nothing of the other side of an edge). Where the
cell has no traced corner of the reflector (its edges), the pixel takes the guided
tent-weighted mean of its reflector's traced pixels within the pattern's spacing - 1
rows and columns (unguided where the guides leave none); an isolated pixel keeps the
raster fallback. Unlike the bilinear fill it replaces, the interpolation is smooth
across the pattern's cells (no 4 x 4 blocks: their creases, the bilinear fill's, were
the largest second differences of the image), and edges inside a reflector stay edges.

Measured on the sewer's wet tunnel (frames 217-276 every 6th, 320 x 240, every
reflector traced): mean FLIP against full density, blocks and its cost at 640 x 480
against the bilinear fill are in docs/heuristic.md ("The reconstruction").

Across frames: the fill is a function of one frame's traced samples (pixel, radiance,
hit distance) and its G-buffer; it keeps no state. The pattern rotates from frame to
frame (``rotation_phase``, passed to ``traced_subset`` and ``fill_skipped`` alike), and a
skipped pixel whose reprojected history is valid takes it instead of a fill
(``complete``, with ``engine/reflection_history.py``'s ``FrameReuse``).

Pixels are flat indices ``row * width + col`` of the G-buffer; ``src`` is each pixel's
index into the round's sources (``Tracer.trace_reflections``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from phrt_usd.model import pixel_kinds
from phrt_usd.model.frame import ReflectionResult, flat_image
from phrt_usd.model.trace_density import LEVEL_RANKS, TRACE_DENSITIES, sparse_floor

#: The ordered-dither (Bayer) ranks of a 4 x 4 block: a density of k/16 traces the pixels
#: of rank below k (``model/trace_density.py``). Its prefixes of 2^j ranks are the regular
#: patterns: rank 0 one pixel of each 4 x 4 block, ranks 0-1 the checkerboard of the 2 x 2
#: grid, 0-3 the 2 x 2 grid, 0-7 the checkerboard, 0-15 every pixel.
BAYER_RANKS = np.array([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]], np.int64)
_RANKS = np.array(LEVEL_RANKS, np.int64)
#: Each density's ``sparse_floor``, by index of TRACE_DENSITIES.
_FLOORS = np.array([sparse_floor(d) for d in TRACE_DENSITIES], np.int64)
#: The regular pattern each density contains (its traced pixels of the largest power of
#: two of ranks): the lattice the fill interpolates on and the reuse's cells are cut by;
#: a density between two powers traces that pattern's pixels and more, which keep their
#: traced values (the fill still interpolates on the coarser lattice).
_REGULAR = 2 ** np.floor(np.log2(_RANKS)).astype(np.int64)
#: Each density's lattice as ``fill_kernels.fill_skipped`` takes it, by index of
#: TRACE_DENSITIES: -q the checkerboard of the grid of spacing q (-1 the checkerboard),
#: s >= 2 the grid of spacing s, 1 none (every pixel traced).
_LATTICE = np.select([_REGULAR == 16, _REGULAR == 8, _REGULAR == 4, _REGULAR == 2],
                     [1, -1, 2, -2], 4).astype(np.int64)  # fmt: skip
#: Side of the square cells of each density's regular pattern that hold one or more of its
#: traced pixels (the reuse's cells: ``engine/reflection_history.py``), by index of
#: TRACE_DENSITIES: 1 at full density, 2 down to a quarter, 4 below.
LEVEL_SPACING = np.where(_REGULAR == 16, 1, np.where(_REGULAR >= 4, 2, 4)).astype(np.int64)
#: Frames after which a density's rotating pattern (``rotation_phase``) has visited every
#: pixel, by index of TRACE_DENSITIES: 16 / 2^j for a regular pattern of 2^j ranks (its
#: traced pixels are one in that many).
LEVEL_PERIOD = (16 // _REGULAR).astype(np.int64)
#: The same by name.
ROTATION_PERIOD = dict(zip(TRACE_DENSITIES, LEVEL_PERIOD.tolist(), strict=True))


#: The rotation of the patterns from frame to frame (``rotation_phase``): the 2 x 2
#: offsets in the order that alternates the checkerboard's parity every frame (so "half"
#: covers its pixels in 2 frames) and visits every offset of a 2 x 2 block in 4 ("quarter");
#: the same order again for the 4 x 4 block's 2 x 2 sub-blocks, so "sixteenth" visits all
#: 16 offsets in 16 frames, each 4 consecutive frames spread over one 2 x 2 block, and
#: "eighth" (whose pattern holds the offsets 0 and (2, 2)) all 8 of its own in 8.
_ROTATION_2X2 = ((0, 0), (0, 1), (1, 1), (1, 0))


def rotation_phase(frame: int) -> tuple[int, int]:
    """The pattern's (row, column) shift at the ``frame``-th frame of a rotating sequence
    (``traced_subset``'s ``phase``): frame k's fine 2 x 2 offset is the k-th of
    _ROTATION_2X2, its coarse one (times 2) the (k // 4)-th; a density of spacing s reads
    the shift modulo s, so every density rotates through its own cell with one phase."""
    fine = _ROTATION_2X2[frame % 4]
    coarse = _ROTATION_2X2[(frame // 4) % 4]
    return fine[0] + 2 * coarse[0], fine[1] + 2 * coarse[1]


def pattern_spacing(density: str) -> int:
    """Rows and columns between the traced pixels of ``density``'s regular pattern along
    an axis of the image (1 at full density; 2 the checkerboard and the 2 x 2 grid, 4 the
    eighth's checkerboard and the 4 x 4 grid): the reach of its fill's lattice steps."""
    return int(LEVEL_SPACING[TRACE_DENSITIES.index(density)])


_NO_IMAGE = np.zeros((0, 3), np.float32)


@dataclass(frozen=True)
class FillGuides:
    """The G-buffer images the fill weighs traced samples by, flat over its H*W pixels:
    normal (H*W, 3) float32 unit, position (H*W, 3) float64 world, depth (H*W,) float32
    view depth; width, height the G-buffer's. ``raster``: the raster frame's fallback
    (H*W, 3), local (H*W, 3) float32 and reflectivity (H*W,) float32 images, from which
    the fill's sky rule reads each pixel's fallback reflection (``fill_kernels``); empty
    arrays: the rule is off."""

    normal: np.ndarray
    position: np.ndarray
    depth: np.ndarray
    width: int
    height: int
    raster: tuple[np.ndarray, np.ndarray, np.ndarray] = (_NO_IMAGE, _NO_IMAGE, _NO_IMAGE[:, 0])

    @classmethod
    def of(cls, gbuffer, raster=None) -> FillGuides:
        """The guides of a ``GBuffer`` (views where its arrays already are flat-able);
        ``raster`` (fallback (H, W, 3), local (H, W, 3), reflectivity (H, W)) the raster
        frame's images for the sky rule, None: off (a stage with transmissive materials,
        whose traced radiance mixes in refraction, passes None)."""
        height, width = gbuffer.shape
        images = cls.raster
        if raster is not None:
            fallback, local, reflectivity = raster
            images = (flat_image(fallback, np.float32, 3), flat_image(local, np.float32, 3),
                      flat_image(reflectivity, np.float32, 1))  # fmt: skip
        return cls(
            flat_image(gbuffer.normal, np.float32, 3),
            flat_image(gbuffer.position, np.float64, 3),
            flat_image(gbuffer.depth, np.float32, 1),
            width,
            height,
            images,
        )


def pixel_levels(density, src: np.ndarray) -> np.ndarray:
    """(n,) int64 index in TRACE_DENSITIES of the density of each pixel's source (``src``
    (n,) int64): ``density`` one of TRACE_DENSITIES for every source, or a sequence of
    them, one per source."""
    if isinstance(density, str):
        return np.full(len(src), TRACE_DENSITIES.index(density), np.int64)
    levels = np.array([TRACE_DENSITIES.index(d) for d in density], np.int64)
    return levels[src] if len(levels) else np.zeros(len(src), np.int64)


def traced_subset(
    pix: np.ndarray, src: np.ndarray, n_sources: int, width: int, density, phase=(0, 0)
) -> np.ndarray:
    """(n,) bool: which of the round's pixels ``pix`` (n,) int64 of sources ``src`` (n,)
    int64 start rays at ``density``, one of TRACE_DENSITIES for every source or a
    sequence of them, one per source: every pixel of a source traced at "full" or with
    fewer pixels than its density's ``sparse_floor``, the pattern's pixels of the others,
    the pattern shifted by ``phase`` (rows, columns)."""
    counts = np.bincount(src, minlength=n_sources)
    row, col = np.divmod(pix, width)
    rank = BAYER_RANKS[(row - int(phase[0])) % 4, (col - int(phase[1])) % 4]
    levels = pixel_levels(density, src)
    on_pattern = rank < _RANKS[levels]
    return (counts[src] < _FLOORS[levels]) | on_pattern


class Fill(NamedTuple):
    """``fill_skipped``'s answer: ``filled`` (m,) bool which skipped pixels got a value,
    and for those k, in their order: ``radiance`` (k, 3) float32, ``hit_distance`` (k,)
    float32 the estimate of their rays' (+inf: leaving the scene), ``low``, ``high`` (k,
    3) float32 per channel the least and the greatest of the samples each was made of."""

    filled: np.ndarray
    radiance: np.ndarray
    hit_distance: np.ndarray
    low: np.ndarray
    high: np.ndarray


def fill_skipped(
    traced_pix: np.ndarray,
    traced_src: np.ndarray,
    radiance: np.ndarray,
    hit_distance: np.ndarray | None,
    skipped_pix: np.ndarray,
    skipped_src: np.ndarray,
    guides: FillGuides,
    density="quarter",
    table: np.ndarray | None = None,
    phase=(0, 0),
    split=None,
) -> Fill:
    """Radiance of the skipped pixels from the traced pixels of the same source around
    them (module docstring; ``fill_kernels``).

    traced_pix, traced_src : (n,) int64 the traced pixels (each once) and their sources
    radiance : (n, 3) float32 traced radiance of those pixels
    hit_distance : (n,) float32 how far each one's reflection ray went (+inf: it left
        the scene; ``ReflectionResult.hit_distance``), None: not known (all alike: the
        fill then has no hit-distance guide)
    skipped_pix, skipped_src : (m,) int64 the skipped pixels and their sources
    guides : the G-buffer's ``FillGuides``
    density : the density the sources were traced at, one of TRACE_DENSITIES but "full"
        for every source, or a sequence of them, one per source (index ``skipped_src``)
    table : (H * W,) int32 all -1, a table the kernels use and leave as they found it (a
        caller tracing round after round keeps one); None: a new one
    phase : (rows, columns) the pattern's shift, as ``traced_subset``'s
    split : None, or ``split(kernel, k, *args, out=outputs)`` calling ``kernel(*args,
        lo, hi, *outputs)`` over slices of rows 0..k (``Tracer._split``: the tracer's
        pool)
    Returns the ``Fill``: the skipped pixels with a traced pixel of their source in their
    cell or within the fill's window got a value, the others keep the fallback."""
    kernels = _fill_kernels()
    if table is None:
        table = np.full(guides.width * guides.height, -1, np.int32)
    if split is None:
        split = one_call
    traced_pix, traced_src = _int64(traced_pix), _int64(traced_src)
    skipped_pix, skipped_src = _int64(skipped_pix), _int64(skipped_src)
    radiance = np.ascontiguousarray(radiance, np.float32)
    n, m = len(traced_pix), len(skipped_pix)
    out_rad, out_hit = np.empty((m, 3), np.float32), np.empty(m, np.float32)
    out_low, out_high = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32)
    ok = np.zeros(m, bool)
    v, curvature = np.empty(n), np.empty((n, 2, 3), np.float32)
    size = (guides.width, guides.height)
    if hit_distance is None:
        hit_distance = np.full(n, np.inf, np.float32)
    kernels.fill_table(table, traced_pix, np.ascontiguousarray(hit_distance, np.float32),
                       guides.depth, v)  # fmt: skip
    try:
        split(
            kernels.fill_curvature, n, table, traced_pix, traced_src, radiance, v,
            _LATTICE[pixel_levels(density, traced_src)], *size, guides.normal,
            guides.position, out=(curvature,),
        )  # fmt: skip
        split(
            kernels.fill_skipped, m, table, traced_src, radiance, v, curvature, traced_pix,
            skipped_pix, skipped_src, _LATTICE[pixel_levels(density, skipped_src)],
            np.array(phase, np.int64), *size, guides.normal, guides.position, guides.depth,
            *guides.raster, out=(out_rad, out_hit, ok, out_low, out_high),
        )  # fmt: skip
    finally:
        kernels.clear_table(table, traced_pix)
    if ok.all():  # the usual case: no copies (a quarter of the fill's time otherwise)
        return Fill(ok, out_rad, out_hit, out_low, out_high)
    return Fill(ok, out_rad[ok], out_hit[ok], out_low[ok], out_high[ok])


def complete(result: ReflectionResult, src, skipped, guides: FillGuides, density, phase,
             reuse, table: np.ndarray, split, start: float) -> ReflectionResult:  # fmt: skip
    """A reduced-density round's ``result`` (its traced, or screen-space, pixels) with its
    skipped pixels reused or filled: the reprojected history where ``reuse`` (an
    ``engine.reflection_history.FrameReuse``, None: none) finds it valid, else filled
    (``fill_skipped``, with ``guides``, ``table`` and ``split``) and the fill blended
    with what history it has (``FrameReuse.accumulate``); its records count every
    covered pixel (hits scaled alike). src (n,) the result's pixels' sources, skipped
    (pixels (m,), their sources (m,), covered pixels per source) from
    ``Tracer._source_pixels``; density and phase as ``Tracer.trace_reflections``';
    ``start`` the round's ``perf_counter`` start (its ``seconds``)."""
    skipped_pix, skipped_src, covered = skipped
    reused_pix = np.zeros(0, np.int64)
    reused_radiance, reused_hit = np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
    if reuse is not None:
        taken, reused_radiance, reused_hit = reuse.reprojected(
            result.pixel_index, src, result.radiance, result.hit_distance, skipped_pix,
            skipped_src, density, split,
        )  # fmt: skip
        reused_pix = skipped_pix[taken]
        skipped_pix, skipped_src = skipped_pix[~taken], skipped_src[~taken]
    fill = fill_skipped(
        result.pixel_index, src, result.radiance, result.hit_distance, skipped_pix,
        skipped_src, guides, density, table, phase=phase, split=split,
    )  # fmt: skip
    fill_pix = skipped_pix if len(fill.radiance) == len(skipped_pix) else skipped_pix[fill.filled]
    fill_radiance, fill_hit = fill.radiance, fill.hit_distance
    if reuse is not None:  # the fill's own arrays: blended in place
        reuse.accumulate(fill_pix, fill_hit, fill_radiance, fill.low, fill.high, split)
    records = [
        dataclasses.replace(
            record,
            pixels=c,
            hits={e: round(n * c / max(record.pixels, 1)) for e, n in record.hits.items()},
        )
        for record, c in zip(result.records, covered.tolist(), strict=True)
    ]
    n, k = len(result.pixel_index), len(reused_pix)
    kinds = np.full(n + k + len(fill_pix), pixel_kinds.FILLED, np.uint8)
    kinds[:n] = pixel_kinds.TRACED if result.kinds is None else result.kinds
    kinds[n : n + k] = pixel_kinds.REUSED
    hit_distance = None
    if result.hit_distance is not None:
        hit_distance = np.concatenate([result.hit_distance, reused_hit, fill_hit])
    return ReflectionResult(
        pixel_index=np.concatenate([result.pixel_index, reused_pix, fill_pix]),
        radiance=np.concatenate([result.radiance, reused_radiance, fill_radiance]),
        records=records,
        rays=result.rays,
        seconds=time.perf_counter() - start,
        kinds=kinds,
        hit_distance=hit_distance,
    )


def one_call(kernel, n: int, *args, out: tuple) -> None:
    """``kernel`` over rows 0..n in one call (``fill_skipped``'s ``split`` by default)."""
    kernel(*args, 0, n, *out)


def _int64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.int64)


def _fill_kernels():
    """The compiled fill (imported on first use: this module is imported by the options,
    long before anything is traced)."""
    from phrt_usd import kernels

    return kernels.load("phrt_usd.engine.trace.fill_kernels")
