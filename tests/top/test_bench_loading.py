"""tools/bench_loading.py measures what it says on a small stage: every child's steps,
the triangles phrt and Embree were given, and peak memory from the child process."""

from __future__ import annotations

import json
import sys

import pytest
from repo_paths import TOOLS
from scenes import cube_stage

if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))
import bench_loading  # noqa: E402


@pytest.mark.slow
def test_bench_loading_reports_every_step(tmp_path, capsys):
    stage = cube_stage(tmp_path / "cube.usda")
    bench_loading.main([str(stage), "--many-meshes", "3x2", "--runs", "1", "--resolution",
                        "32x24", "--json"])  # fmt: skip
    result, many = json.loads(capsys.readouterr().out)["stages"]
    # The written stage: 3 meshes of 2 x 2 quads, 2 triangles a quad.
    assert many["phrt"]["info"]["triangles"] == 3 * 2 * 2 * 2
    assert many["phrt"]["info"]["elements"] == 3
    phrt, embree, usd = result["phrt"], result["embree"], result["usd"]
    # USD's Cube: 6 faces of 2 triangles each, the same for phrt and Embree.
    assert phrt["info"]["triangles"] == embree["info"]["triangles"] == 12
    steps = {"import", "read", "bvh", "renderer", "warm_up", "first_frame", "load"}
    assert set(phrt["seconds"]) == steps
    assert all(v["median"] > 0 for v in phrt["seconds"].values())
    seconds = {name: entry["median"] for name, entry in phrt["seconds"].items()}
    # One run: load is exactly read + BVH of that run (float sum, rounding aside).
    assert seconds["load"] == pytest.approx(seconds["read"] + seconds["bvh"])
    assert usd["info"]["prims"] >= 2 and usd["seconds"]["usd_read"]["median"] > 0
    # Peak memory is the child's own: more than an empty interpreter (~10 MB) and its
    # steps' peaks never above the process's.
    assert 10 < phrt["peak_mb"]["read"] <= phrt["peak_mb"]["process"]
