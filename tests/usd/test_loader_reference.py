"""The stage reader against a plain per-face reading of the same stage.

A stage of many meshes with many polygons (3 to 8 sides, and faces of fewer than 3
vertices), ``holeIndices`` (one outside the faces), ``leftHanded`` meshes, negative-scale
transforms, every primvar interpolation (indexed ones too), authored and smooth normals,
GeomSubset material bindings, native instances with different bindings, and a
PointInstancer with a masked instance is read by ``read_stage``; every element's
triangles (world positions, corner normals, albedo, texture coordinates and material)
must equal, in order, what a loop over each face computes from USD's own answers
(``ComputeFlattened``, ``XformCache``, ``ComputeInstanceTransformsAtTime``,
``ComputeBoundMaterial``) with the rules ``usd/meshes.py`` documents: fan triangles
(0, k, k+1) of each drawn face, the winding flipped by ``leftHanded`` and again by a
negative-determinant transform, smooth normals area-weighted over the drawn triangles.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade, Vt
from textured_stages import define_texture, write_one_colour_png

import phrt_usd  # noqa: F401  (registers the schema)
from phrt_usd.usd.stage import read_stage

#: Stage units: centimetres, so the reader's scaling to metres is part of the check.
METERS_PER_UNIT = 0.01
#: Meshes of the polygon group; faces per mesh.
MESHES = 48
FACES = 40
#: Material colours (diffuseColor) by material name; ``/Looks/Tex`` is textured (the
#: corners of its triangles carry ``st``).
COLOURS = {"Red": (0.8, 0.1, 0.1), "Green": (0.1, 0.7, 0.2), "Blue": (0.1, 0.2, 0.9)}

#: Positions are compared in metres: the stage spans ~10 m and the reader computes in
#: float64, so 1e-9 m is far above rounding and far below any real difference.
POSITION_TOL = 1e-9
#: Normals, albedo and uv are float32 in the scene: a few float32 ulps of a unit value.
FLOAT32_TOL = 2e-6


def _material(stage, name, colour, texture=None):
    """A UsdPreviewSurface of ``colour``, its diffuseColor read from ``texture`` if given."""
    mat = UsdShade.Material.Define(stage, f"/Looks/{name}")
    shader = UsdShade.Shader.Define(stage, f"/Looks/{name}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    diffuse = shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    diffuse.Set(Gf.Vec3f(*colour))
    if texture is not None:
        tex = define_texture(stage, f"/Looks/{name}/Image", texture)
        diffuse.ConnectToSource(tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return mat


def _rotation(rng) -> Gf.Vec3d:
    return Gf.Vec3d(*rng.uniform(-180.0, 180.0, 3).tolist())


def _polygon_mesh(stage, path, rng, index: int) -> UsdGeom.Mesh:
    """A mesh of FACES random polygons over a jittered point cloud, with the primvars
    and topology variations its index selects."""
    counts = rng.integers(3, 9, FACES)
    counts[rng.integers(0, FACES, 2)] = rng.integers(0, 3, 2)  # faces with no area
    n_points = int(counts.sum()) // 2 + 8
    points = rng.normal(0.0, 20.0, (n_points, 3))
    indices = rng.integers(0, n_points, int(counts.sum()))
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(indices.astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    if index % 3 == 1:
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    if index % 4 == 2:  # some holes, one outside the faces (ignored)
        holes = sorted(set(rng.integers(0, FACES, 5).tolist())) + [FACES + 7]
        mesh.CreateHoleIndicesAttr(holes)
    xf = UsdGeom.Xformable(mesh)
    xf.AddTranslateOp().Set(Gf.Vec3d(*rng.uniform(-400.0, 400.0, 3).tolist()))
    xf.AddRotateXYZOp().Set(_rotation(rng))
    scale = rng.uniform(0.5, 2.0, 3)
    if index % 5 == 3:
        scale[index % 3] *= -1.0  # a mirroring transform: the winding flips
    xf.AddScaleOp().Set(Gf.Vec3d(*scale.tolist()))
    n_faces, n_corners = FACES, int(counts.sum())
    sizes = {"constant": 1, "uniform": n_faces, "vertex": n_points, "faceVarying": n_corners}
    interps = list(sizes)
    pv_api = UsdGeom.PrimvarsAPI(mesh)
    colour_interp = interps[index % 4]
    if index % 6 != 5:  # the rest have no displayColor
        colour = pv_api.CreatePrimvar(
            "displayColor", Sdf.ValueTypeNames.Color3fArray, colour_interp
        )
        if index % 7 == 0 and colour_interp != "constant":  # indexed
            colour.Set(Vt.Vec3fArray.FromNumpy(rng.uniform(0, 1, (5, 3)).astype(np.float32)))
            colour.SetIndices(Vt.IntArray.FromNumpy(
                rng.integers(0, 5, sizes[colour_interp]).astype(np.int32)))  # fmt: skip
        else:
            values = rng.uniform(0, 1, (sizes[colour_interp], 3)).astype(np.float32)
            colour.Set(Vt.Vec3fArray.FromNumpy(values))
    if index % 3 == 0:  # authored normals, interpolation cycling; others smooth
        interp = ["faceVarying", "vertex", "uniform"][(index // 3) % 3]
        normals = rng.normal(0.0, 1.0, (sizes[interp], 3)).astype(np.float32)
        pv = pv_api.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, interp)
        pv.Set(Vt.Vec3fArray.FromNumpy(normals))
    st_interp = interps[(index + 1) % 4]
    st = pv_api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, st_interp)
    st.Set(Vt.Vec2fArray.FromNumpy(rng.uniform(0, 1, (sizes[st_interp], 2)).astype(np.float32)))
    return mesh


def _bind(prim, material) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def heavy_stage(texture, seed: int = 7) -> Usd.Stage:
    """The stage of the module doc, made the same way for every seed (``texture``: an
    image file for the textured material)."""
    rng = np.random.default_rng(seed)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, METERS_PER_UNIT)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 3000))
    cam.CreateClippingRangeAttr(Gf.Vec2f(1.0, 10000.0))
    UsdLux.DomeLight.Define(stage, "/Sky")
    mats = {name: _material(stage, name, colour) for name, colour in COLOURS.items()}
    names = list(mats)
    textured = _material(stage, "Tex", (1.0, 1.0, 1.0), texture)
    for m in range(MESHES):
        mesh = _polygon_mesh(stage, f"/World/Polys/G{m // 10}/M{m}", rng, m)
        if m % 8 == 6:
            _bind(mesh.GetPrim(), textured)
        elif m % 3 != 2:
            _bind(mesh.GetPrim(), mats[names[m % 3]])
        if m % 4 == 1:  # two subsets bind other materials to some faces
            faces = rng.permutation(FACES)
            for k, name in enumerate(names[1:]):
                subset = UsdGeom.Subset.CreateGeomSubset(
                    mesh, f"part{k}", UsdGeom.Tokens.face,
                    Vt.IntArray(faces[k * 9 : k * 9 + 9].tolist()), "materialBind",
                )  # fmt: skip
                _bind(subset.GetPrim(), mats[name])
    # Native instancing: three instances of one prototype, two bound differently.
    proto = stage.DefinePrim("/Protos/Thing", "Xform")
    stage.GetPrimAtPath("/Protos").SetSpecifier(Sdf.SpecifierClass)
    for k in range(2):
        _polygon_mesh(stage, f"/Protos/Thing/Part{k}", rng, 10 + k)
    for i in range(3):
        inst = stage.DefinePrim(f"/World/Instances/I{i}", "Xform")
        inst.GetReferences().AddInternalReference(proto.GetPath())
        inst.SetInstanceable(True)
        UsdGeom.Xformable(inst).AddTranslateOp().Set(Gf.Vec3d(i * 300.0, 0.0, -500.0))
        if i:
            _bind(inst, mats[names[i]])
    # A PointInstancer: a mesh prototype and a two-mesh prototype, one instance masked.
    pi = UsdGeom.PointInstancer.Define(stage, "/World/Scatter")
    UsdGeom.Xformable(pi).AddTranslateOp().Set(Gf.Vec3d(0.0, 200.0, 0.0))
    p0 = _polygon_mesh(stage, "/World/Scatter/Protos/Rock", rng, 4)
    group = UsdGeom.Xform.Define(stage, "/World/Scatter/Protos/Pair")
    group.AddRotateYOp().Set(30.0)
    for k in range(2):
        _polygon_mesh(stage, f"/World/Scatter/Protos/Pair/P{k}", rng, 20 + k)
    pi.CreatePrototypesRel().SetTargets([p0.GetPath(), group.GetPath()])
    n = 7
    pi.CreateProtoIndicesAttr(Vt.IntArray([i % 2 for i in range(n)]))
    positions = rng.uniform(-300, 300, (n, 3)).astype(np.float32)
    pi.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(positions))
    quats = rng.normal(0, 1, (n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    pi.CreateOrientationsAttr([Gf.Quath(*q.tolist()) for q in quats])
    pi.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(rng.uniform(0.5, 1.5, (n, 3)).astype(np.float32)))
    pi.InvisIds([3], Usd.TimeCode.Default())
    return stage


# ---- the per-face reference --------------------------------------------------------


def _shader_colour(material) -> np.ndarray:
    shader = UsdShade.Shader(material.GetPrim().GetChild("Surface"))
    return np.array(shader.GetInput("diffuseColor").Get(), np.float64)


def _flattened(prim, name):
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
    if not pv or not pv.HasAuthoredValue():
        return None
    return np.asarray(pv.ComputeFlattened(), np.float64), str(pv.GetInterpolation())


def _pick(values, interp, face, point, corner):
    """One corner's value of a flattened primvar."""
    return values[{"constant": 0, "uniform": face, "vertex": point, "varying": point,
                   "faceVarying": corner}[interp]]  # fmt: skip


def _normal_matrix(m3: np.ndarray) -> np.ndarray:
    """The inverse transpose (row vectors): normals stay normal to transformed faces."""
    return np.linalg.inv(m3).T


def _unit(v: np.ndarray) -> np.ndarray:
    """``v`` normalised; +Z for a zero vector (the reader's fallback)."""
    length = np.linalg.norm(v)
    return v / length if length > 1e-30 else np.array([0.0, 0.0, 1.0])


def reference_mesh(prim, world: np.ndarray) -> list[dict]:
    """Each drawn triangle of a UsdGeomMesh placed by ``world`` (4, 4) row-vector matrix
    in stage units, one face at a time: positions (3, 3) metres, normals (3, 3), albedo
    (3, 3), st (3, 2), diffuse of the face's material or None."""
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    counts = list(mesh.GetFaceVertexCountsAttr().Get())
    indices = list(mesh.GetFaceVertexIndicesAttr().Get())
    holes = set(mesh.GetHoleIndicesAttr().Get() or [])
    left = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    face_material = [UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]] * len(counts)
    for subset in UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets():
        bound = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()[0]
        for f in subset.GetIndicesAttr().Get():
            face_material[f] = bound
    corners = []  # (face, [corner ids], [point ids])
    start = 0
    for face, count in enumerate(counts):
        if count >= 3 and face not in holes:
            for k in range(1, count - 1):
                ids = [start, start + k, start + k + 1]
                if left:
                    ids = [ids[0], ids[2], ids[1]]
                corners.append((face, ids, [indices[c] for c in ids]))
        start += count
    normals = _flattened(prim, "normals")
    smooth = None
    if normals is None:  # area-weighted over the drawn triangles, in mesh space
        smooth = np.zeros_like(points)
        for _, _, pts in corners:
            a, b, c = points[pts]
            smooth[pts] += np.cross(b - a, c - a)
    colour = _flattened(prim, "displayColor")
    st = _flattened(prim, "st")
    m3, shift = world[:3, :3], world[3, :3]
    nmat = _normal_matrix(m3)
    flip = np.linalg.det(m3) < 0
    out = []
    for face, ids, pts in corners:
        a, b, c = points[pts]
        face_n = _unit(np.cross(b - a, c - a))
        tri = {"positions": [], "normals": [], "albedo": [], "st": []}
        material = face_material[face]
        diffuse = _shader_colour(material) if material else None
        if material and material.GetPath() == "/Looks/Tex":
            diffuse = None  # textured: its albedo is the texture's (not compared here)
        for corner, point in zip(ids, pts, strict=True):
            tri["positions"].append((points[point] @ m3 + shift) * METERS_PER_UNIT)
            if normals is not None:
                n = np.nan_to_num(_pick(*normals, face, point, corner))
            else:
                n = _unit(smooth[point]) if np.linalg.norm(smooth[point]) > 0 else face_n
            tri["normals"].append(_unit(_unit(n) @ nmat))
            if diffuse is not None:
                tri["albedo"].append(diffuse)
            elif colour is not None:
                tri["albedo"].append(np.clip(_pick(*colour, face, point, corner), 0, None))
            else:
                tri["albedo"].append(np.full(3, 0.5))
            tri["st"].append(_pick(*st, face, point, corner)[:2])
        order = [0, 2, 1] if flip else [0, 1, 2]
        out.append({k: np.asarray(v)[order] for k, v in tri.items()}
                   | {"diffuse": diffuse, "textured": bool(material) and diffuse is None})
    return out


def reference_elements(stage) -> dict[str, list[dict]]:
    """Element path → its triangles (``reference_mesh``), for the meshes of the stage and
    of its PointInstancer."""
    cache = UsdGeom.XformCache()
    elements = {}
    it = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()))
    for prim in it:
        if prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            pi = UsdGeom.PointInstancer(prim)
            protos = pi.GetPrototypesRel().GetTargets()
            xforms = pi.ComputeInstanceTransformsAtTime(
                Usd.TimeCode.Default(), Usd.TimeCode.Default(),
                UsdGeom.PointInstancer.IncludeProtoXform, UsdGeom.PointInstancer.IgnoreMask,
            )  # fmt: skip
            world = np.array(cache.GetLocalToWorldTransform(prim))
            for i, index in enumerate(pi.GetProtoIndicesAttr().Get()):
                if i in (pi.GetInvisibleIdsAttr().Get() or []):
                    continue
                root = stage.GetPrimAtPath(protos[index])
                for g in Usd.PrimRange(root):
                    if not g.IsA(UsdGeom.Mesh):
                        continue
                    rel = np.array(cache.ComputeRelativeTransform(g, root)[0])
                    suffix = "/" + str(g.GetPath().MakeRelativePath(root.GetPath()))
                    if g == root:
                        rel, suffix = np.eye(4), ""
                    m = rel @ np.array(xforms[i]) @ world
                    elements[f"{prim.GetPath()}.instance[{i}]{suffix}"] = reference_mesh(g, m)
        elif prim.IsA(UsdGeom.Mesh):
            elements[str(prim.GetPath())] = reference_mesh(
                prim, np.array(cache.GetLocalToWorldTransform(prim))
            )
    return elements


# ---- the test ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def read_and_reference(tmp_path_factory):
    texture = tmp_path_factory.mktemp("loader") / "grey.png"
    write_one_colour_png(texture, (0.5, 0.5, 0.5))
    stage = heavy_stage(str(texture))
    return read_stage(stage).scene, reference_elements(stage)


@pytest.mark.slow
def test_heavy_stage_has_what_the_reference_covers(read_and_reference):
    scene, ref = read_and_reference
    # The stage holds what the module doc lists: 48 meshes, 3 x 2 instance proxies and
    # the instancer's 6 visible instances of 7 (4 of one mesh, 2 of two meshes).
    assert len(ref) == MESHES + 3 * 2 + 4 + 2 * 2
    assert [e.path for e in scene.elements] == list(ref)
    textured = [t["textured"] for triangles in ref.values() for t in triangles]
    assert 0 < sum(textured) < len(textured)  # some triangles carry st, most do not
    assert scene.geometry.corner_uv is not None


@pytest.mark.slow
def test_loader_triangles_equal_a_per_face_reading(read_and_reference):
    scene, ref = read_and_reference
    geo = scene.geometry
    table = scene.materials
    for e, element in enumerate(scene.elements):
        rows = np.flatnonzero(geo.tri_element == e)
        expected = ref[element.path]
        assert len(rows) == len(expected), element.path
        got_pos = geo.vertices[geo.triangles[rows]]
        want = {k: np.array([t[k] for t in expected]) for k in ("positions", "normals", "albedo")}
        np.testing.assert_allclose(got_pos, want["positions"], atol=POSITION_TOL, rtol=0,
                                   err_msg=element.path)  # fmt: skip
        np.testing.assert_allclose(geo.corner_normals[rows], want["normals"], atol=FLOAT32_TOL * 4,
                                   rtol=0, err_msg=element.path)  # fmt: skip
        plain = ~np.array([t["textured"] for t in expected], bool)
        np.testing.assert_allclose(geo.corner_albedo[rows][plain], want["albedo"][plain],
                                   atol=FLOAT32_TOL, rtol=0, err_msg=element.path)  # fmt: skip
        if not plain.all():  # the textured ones carry their st, every interpolation
            np.testing.assert_allclose(
                geo.corner_uv[rows][~plain], np.array([t["st"] for t in expected])[~plain],
                atol=FLOAT32_TOL, rtol=0, err_msg=element.path,
            )  # fmt: skip
        for row, tri in zip(rows, expected, strict=True):
            material = geo.tri_material[row]
            if tri["textured"]:
                assert table.textures[material] is not None, element.path
            elif tri["diffuse"] is None:
                assert material == 0, element.path  # row 0: no material
            else:
                np.testing.assert_allclose(table.diffuse[material], tri["diffuse"], atol=1e-7)
