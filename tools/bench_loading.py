"""Loading benchmark: how long phrt takes to read a stage, build its BVH and render the
first frame, and how much memory that takes, against USD's own plain read of the same
stage and Embree's own build of the same triangles.

    uv run python tools/bench_loading.py STAGE [STAGE ...] [--runs 3]
        [--resolution 320x240] [--mode hybrid] [--threads N] [--json]
        [--many-meshes 5000x12]

``--many-meshes MxQ`` adds a stage written here to a temporary directory: M meshes of
Q x Q quads each (2 Q² triangles, a constant displayColor, no material, side by side
on a grid), the many-small-meshes case (5000x12: 1.44 M triangles, as many as the
chess set below in 5000 meshes instead of 21).

Every measurement runs in a fresh child process (this file with ``--child``), ``--runs``
times; printed are the medians over the runs (and the spread, min-max) and the peak
resident memory, the child's own ``ru_maxrss`` after each of its steps (the largest over
the runs). Three kinds of child:

* **usd** -- USD's plain read: ``Usd.Stage.Open`` and a traversal of every prim
  (instance proxies included) reading every attribute's value at the default time.
  What any reader of the stage pays before it has done anything with the values (what
  ``usdcat`` reads before it writes; the usd-core wheel ships no ``usdcat`` binary).
* **embree** -- Embree's own build: the stage read by phrt, its triangles as phrt hands
  them to Embree (float32 vertices relative to the scene's origin, int32 triangles),
  the scene freed, then one ``embreex`` scene of one triangle mesh built and committed
  (the time of that build only).
* **phrt** -- the steps of a render's start, each timed: ``import`` of the renderer,
  ``read`` (``open_stage``: open, traverse, triangulate, place), ``bvh`` (the tracer's
  ``Bvh``: its copies, its per-triangle table and Embree's build; freed again), then the
  renderer as ``phrt render`` makes it (``FrameRenderer``: raster upload, and its own BVH
  when the stage has reflectors to trace), its ``warm_up`` (the one-time work of the
  first frame: programs, tables, static shadow maps) and the ``first frame``.
  *load* = read + bvh.

The figures depend on what else runs on the machine: compare ratios from one run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CHILD_KINDS = ("usd", "embree", "phrt")


def _peak_mb() -> float:
    """This process's peak resident memory so far, MB (Linux reports KB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _Steps:
    """Seconds and peak MB after each named step of a child."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.peak_mb: dict[str, float] = {}
        self.info: dict[str, object] = {}

    def time(self, name: str, fn):
        start = time.perf_counter()
        value = fn()
        self.seconds[name] = time.perf_counter() - start
        self.peak_mb[name] = _peak_mb()
        return value

    def result(self) -> dict:
        return {"seconds": self.seconds, "peak_mb": self.peak_mb, "info": self.info}


def _child_usd(stage_path: str, steps: _Steps, args) -> None:
    from pxr import Usd

    def plain_read():
        stage = Usd.Stage.Open(stage_path)
        prims = values = 0
        for prim in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()):
            prims += 1
            for attr in prim.GetAttributes():
                attr.Get()
                values += 1
        steps.info.update(prims=prims, values=values)
        return stage

    steps.time("usd_read", plain_read)


def _child_embree(stage_path: str, steps: _Steps, args) -> None:
    import gc

    import numpy as np
    from embreex import rtcore as rtc
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    from phrt_usd.usd.stage import open_stage

    scene = open_stage(stage_path).scene
    geo = scene.geometry
    vertices = np.ascontiguousarray(geo.vertices - scene.origin, dtype=np.float32)
    triangles = np.ascontiguousarray(geo.triangles, dtype=np.int32)
    steps.info["triangles"] = len(triangles)
    del scene, geo
    gc.collect()
    device = rtc.EmbreeDevice()

    def build():
        bvh = rtcs.EmbreeScene(device)
        TriangleMesh(bvh, vertices, triangles)
        probe = np.zeros((1, 3), dtype=np.float32)
        bvh.run(probe, probe + np.float32(1.0))  # embreex commits on the first query
        return bvh

    steps.time("embree_build", build)


def _child_phrt(stage_path: str, steps: _Steps, args) -> None:
    import gc

    def imports():
        from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
        from phrt_usd.engine.trace.bvh import Bvh
        from phrt_usd.usd.stage import open_stage

        return FrameRenderer, RenderOptions, Bvh, open_stage

    FrameRenderer, RenderOptions, Bvh, open_stage = steps.time("import", imports)
    stage_scene = steps.time("read", lambda: open_stage(stage_path))
    scene = stage_scene.scene
    steps.info.update(
        triangles=int(scene.geometry.triangle_count),
        vertices=len(scene.geometry.vertices),
        elements=len(scene.elements),
        reflectors=len(scene.reflector_ids),
    )
    bvh = steps.time("bvh", lambda: Bvh(scene, threads=args.threads or 1))
    del bvh
    gc.collect()
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    options = {"width": width, "height": height, "mode": args.mode}
    if args.threads:
        options["threads"] = args.threads
    renderer = steps.time("renderer", lambda: FrameRenderer(stage_scene, RenderOptions(**options)))
    start = stage_scene.frame_range[0]
    steps.time("warm_up", lambda: renderer.plan([start]))
    steps.time("first_frame", lambda: renderer.render(start))
    steps.info["primary"] = renderer.primary
    renderer.close()


def run_child(kind: str, stage_path: str, args) -> None:
    """One measurement in this process: print its JSON on stdout."""
    steps = _Steps()
    {"usd": _child_usd, "embree": _child_embree, "phrt": _child_phrt}[kind](
        stage_path, steps, args
    )
    print(json.dumps(steps.result()))


def measure(kind: str, stage: str, args) -> dict:
    """Run one child; its steps plus the child's whole peak RSS (``os.wait4``)."""
    command = [sys.executable, __file__, "--child", kind, stage,
               "--resolution", args.resolution, "--mode", args.mode]  # fmt: skip
    if args.threads:
        command += ["--threads", str(args.threads)]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(command, stdout=out, stderr=err, cwd=REPO, text=True)
        _, status, usage = os.wait4(proc.pid, 0)  # the child's own resource usage
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        if proc.returncode != 0:
            raise SystemExit(f"{kind} child failed on {stage}:\n{err.read().strip()[-2000:]}")
        result = json.loads(out.read().strip().splitlines()[-1])
    result["peak_mb"]["process"] = usage.ru_maxrss / 1024.0
    return result


def _median(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def bench_stage(stage: str, args) -> dict:
    """Every child kind ``args.runs`` times on ``stage``: medians of each step's seconds,
    the largest peak MB after each step, the children's info."""
    out: dict = {"stage": stage}
    for kind in CHILD_KINDS:
        runs = [measure(kind, stage, args) for _ in range(args.runs)]
        steps = runs[0]["seconds"].keys()
        out[kind] = {
            "seconds": {s: _median([r["seconds"][s] for r in runs]) for s in steps},
            "peak_mb": {s: max(r["peak_mb"][s] for r in runs) for s in runs[0]["peak_mb"]},
            "info": runs[0]["info"],
        }
        if kind == "phrt":
            loads = [r["seconds"]["read"] + r["seconds"]["bvh"] for r in runs]
            out[kind]["seconds"]["load"] = _median(loads)
    return out


def _row(result: dict) -> list[str]:
    usd, emb, phrt = result["usd"], result["embree"], result["phrt"]
    s, mb = phrt["seconds"], phrt["peak_mb"]

    def sec(entry) -> str:
        return f"{entry['median']:.2f} ({entry['min']:.2f}-{entry['max']:.2f})"

    return [
        Path(result["stage"]).name,
        f"{phrt['info']['triangles']:,}",
        f"{sec(usd['seconds']['usd_read'])} / {usd['peak_mb']['usd_read']:.0f} MB",
        sec(emb["seconds"]["embree_build"]),
        f"{sec(s['read'])} / {mb['read']:.0f} MB",
        f"{sec(s['bvh'])} / {mb['bvh']:.0f} MB",
        sec(s["load"]),
        f"{sec(s['renderer'])} + {sec(s['warm_up'])}",
        f"{1000 * s['first_frame']['median']:.0f} ms",
        f"{mb['process']:.0f} MB",
    ]


HEADER = [
    "stage", "triangles", "USD plain read / peak", "Embree build", "phrt read / peak",
    "BVH / peak", "load (read + BVH)", "renderer + warm-up", "first frame", "peak (process)",
]  # fmt: skip


def many_meshes_stage(path: Path, meshes: int, quads: int) -> Path:
    """Write the ``--many-meshes`` stage (module doc) to ``path``."""
    import numpy as np
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    k = quads + 1
    grid = np.stack(np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k)), -1).reshape(-1, 2)
    points = np.column_stack([grid[:, 0], np.zeros(len(grid)), grid[:, 1]])
    i, j = np.meshgrid(np.arange(quads), np.arange(quads))
    a = (j * k + i).ravel()
    quad_corners = np.stack([a, a + k, a + k + 1, a + 1], 1).ravel()
    indices = Vt.IntArray.FromNumpy(quad_corners.astype(np.int32))
    counts = Vt.IntArray.FromNumpy(np.full(quads * quads, 4, np.int32))
    side = int(np.ceil(np.sqrt(meshes)))
    for m in range(meshes):
        mesh = UsdGeom.Mesh.Define(stage, f"/World/G{m // 100}/M{m}")
        shifted = points + [m % side * 1.1, 0.0, m // side * 1.1]
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(shifted.astype(np.float32)))
        mesh.CreateFaceVertexCountsAttr(counts)
        mesh.CreateFaceVertexIndicesAttr(indices)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([(0.5, 0.6, 0.7)])
    stage.GetRootLayer().Save()
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stages", nargs="*")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--resolution", default="320x240")
    parser.add_argument("--mode", default="hybrid")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--json", action="store_true", help="One JSON object on stdout.")
    parser.add_argument("--many-meshes", metavar="MxQ", help="Add M meshes of QxQ quads.")
    parser.add_argument("--child", choices=CHILD_KINDS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        run_child(args.child, args.stages[0], args)
        return
    with tempfile.TemporaryDirectory(prefix="phrt-bench-loading-") as tmp:
        stages = list(args.stages)
        if args.many_meshes:
            meshes, quads = (int(v) for v in args.many_meshes.lower().split("x"))
            name = f"many_meshes_{meshes}x{quads}.usdc"
            stages.append(str(many_meshes_stage(Path(tmp) / name, meshes, quads)))
        if not stages:
            parser.error("no stage: give STAGE paths or --many-meshes")
        results = [bench_stage(stage, args) for stage in stages]
    if args.json:
        print(json.dumps({"runs": args.runs, "resolution": args.resolution,
                          "mode": args.mode, "stages": results}, indent=2))  # fmt: skip
        return
    print(f"medians of {args.runs} runs (min-max), seconds; peak RSS of the child process")
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for result in results:
        print("| " + " | ".join(_row(result)) + " |")


if __name__ == "__main__":
    main()
