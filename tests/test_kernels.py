"""The two compiled forms of the kernels (``phrt_usd.kernels``): the ahead-of-time build
is the JIT kernels' own code, found only for the sources it was built from."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phrt_usd import kernels
from phrt_usd.model import surface_kernels


@pytest.fixture(scope="module")
def aot():
    """The ahead-of-time build of the current sources (built here when missing: the
    set-up normally has)."""
    kernels.build_aot()
    kernels._loaded.clear()
    yield kernels.load("phrt_usd.model.surface_kernels")
    kernels._loaded.clear()


def test_load_prefers_the_build_of_these_sources(aot):
    assert kernels.form("phrt_usd.model.surface_kernels") == "aot"
    # Every kernel the module's warm-up compiles is in the build.
    assert {"derive", "hit_geometry", "hit_albedo"} <= set(vars(aot))


def test_aot_and_jit_give_the_same_bits(aot):
    """Same source, same numba, same options: identical results on random hits."""
    rng = np.random.default_rng(11)
    n_tri, m = 50, 3000
    frame = rng.normal(size=(n_tri, 4, 3))
    frame[:, 3] /= np.linalg.norm(frame[:, 3], axis=1, keepdims=True)
    corners = rng.normal(size=(n_tri, 3, 6)).astype(np.float32)
    tri = rng.integers(0, n_tri, m).astype(np.int64)
    u = rng.uniform(0, 0.5, m).astype(np.float32)
    v = rng.uniform(0, 0.5, m).astype(np.float32)
    d = rng.normal(size=(m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    results = []
    for form in (aot, surface_kernels):
        pos, ng = np.empty((m, 3)), np.empty((m, 3))
        ns, alb = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32)
        form.hit_geometry(tri, u, v, d, frame, corners, pos, ng, ns)
        form.hit_albedo(tri, u, v, corners, alb)
        results.append((pos, ng, ns, alb))
    for a, b in zip(*results, strict=True):
        np.testing.assert_array_equal(a, b)


def test_other_argument_types_run_the_jit_kernel(aot):
    """The build reads an array as the dtype it was built for: an int32 index array
    where int64 is expected must not reach it (it would read past the buffer). The
    guard sends the call to the JIT kernel instead and notes it."""
    corners = np.arange(2 * 3 * 6, dtype=np.float32).reshape(2, 3, 6)
    out = np.zeros((2, 3), np.float32)
    zeros = np.zeros(2, np.float32)
    earlier = set(kernels.FALLBACKS)  # other tests' (the suite fails on them anyway)
    aot.hit_albedo(np.array([1, 0], np.int32), zeros, zeros, corners, out)
    this = kernels.FALLBACKS - earlier
    kernels.FALLBACKS.difference_update(this)  # this test's own, expected fallback
    assert this == {
        "phrt_usd.model.surface_kernels.hit_albedo(int32[1d C], float32[1d C], "
        "float32[1d C], float32[3d C], float32[2d C])"
    }
    np.testing.assert_array_equal(out, corners[[1, 0], 0, 3:])  # weights (1, 0, 0)
    out[:] = 0
    aot.hit_albedo(np.array([1, 0], np.int64), zeros, zeros, corners, out)
    np.testing.assert_array_equal(out, corners[[1, 0], 0, 3:])
    assert kernels.FALLBACKS == earlier


#: What a build's argument can be: an array of a dtype, rank and required layout, None,
#: or a scalar (the sidecar's "scalar" / "none" / [dtype, ndim, layout]).
_DTYPES = ["float32", "float64", "int32", "int64", "uint32", "bool"]
_EXPECTED = st.one_of(
    st.just("scalar"),
    st.just("none"),
    st.tuples(st.sampled_from(_DTYPES), st.integers(1, 3), st.sampled_from(["C", "A"])),
)


def _value(kind):
    """An argument value built from ``kind`` = (what, dtype, ndim, strided)."""
    what, dtype, ndim, strided = kind
    if what == "array":
        a = np.zeros((4,) * ndim, dtype)
        return a[::2] if strided else a
    return {"none": None, "int": 3, "float": 0.5, "float32": np.float32(1),
            "swapped": np.zeros(4, ">f8"), "longlong": np.zeros(4, np.longlong),
            "subclass": np.zeros((3, 3)).view(np.matrix)}[what]  # fmt: skip


def _fits_one_by_one(args, expected) -> bool:
    """The guard's rule, argument by argument in Python: the reference for
    ``kernel_guard.c``'s ``fits`` (numpy's dtype equality, exact rank and class)."""
    if len(args) != len(expected):
        return False
    for value, e in zip(args, expected, strict=True):
        if e == "scalar":
            ok = value is not None and type(value) is not np.ndarray
        elif e == "none":
            ok = value is None
        else:
            ok = (type(value) is np.ndarray and value.dtype == np.dtype(e[0])
                  and value.ndim == e[1] and (value.flags.c_contiguous or e[2] != "C"))  # fmt: skip
        if not ok:
            return False
    return True


_KIND = st.tuples(
    st.sampled_from(["array", "array", "none", "int", "float", "float32", "swapped",
                     "longlong", "subclass"]),
    st.sampled_from(_DTYPES),
    st.integers(1, 3),
    st.booleans(),
)  # fmt: skip


@settings(max_examples=400, deadline=None)
@given(st.lists(_EXPECTED, max_size=8), st.data())
def test_guard_is_the_argument_by_argument_rule(aot, expected, data):
    """The C guard accepts exactly the calls the per-argument rule accepts: a wrong
    dtype, byte order, rank, layout, None, array subclass or argument count never
    reaches a build (near misses are drawn: each argument often of its expected kind)."""
    fits = kernels._aot_module()[2]
    kinds = []
    for e in expected:
        near = (("array", e[0], e[1], data.draw(st.booleans())) if isinstance(e, tuple)
                else ("none", "float32", 1, False) if e == "none"
                else ("float", "float32", 1, False))  # fmt: skip
        kinds.append(data.draw(st.one_of(st.just(near), _KIND)))
    extra = data.draw(st.integers(-1, 1))
    args = tuple(map(_value, kinds))
    args = args[:-1] if extra < 0 else args + (0.0,) * extra
    spec = kernels.guard_spec([list(e) if isinstance(e, tuple) else e for e in expected])
    assert fits(args, spec) == _fits_one_by_one(args, expected)


def test_a_changed_source_names_another_build(monkeypatch, tmp_path):
    """The build's name hashes every source: an edited kernel never loads an old build."""
    before = kernels.source_hash()
    edited = tmp_path / "surface_kernels.py"
    original = kernels._source_path("phrt_usd.model.surface_kernels")
    edited.write_bytes(original.read_bytes() + b"\n# edited\n")
    real = kernels._source_path
    monkeypatch.setattr(
        kernels,
        "_source_path",
        lambda name: edited if name == "phrt_usd.model.surface_kernels" else real(name),
    )
    assert kernels.source_hash() != before


def test_only_kernel_modules_load():
    with pytest.raises(ValueError):
        kernels.load("phrt_usd.model.surface")


def test_literal_variants_are_not_exported():
    """A kernel called from another with a constant gets a variant with that constant
    folded in; the ahead-of-time build must not export it (the C guard cannot tell a
    literal True from any other bool, so it would run the folded code for False too)."""
    import numba

    from phrt_usd.kernels import exported_signatures

    @numba.njit
    def pick(x, flag):
        return x + 1.0 if flag else x - 1.0

    @numba.njit
    def caller(x):
        return pick(x, True)

    caller(1.0)  # compiles pick with a literal flag folded in
    pick(1.0, False)  # the variant a Python call compiles
    literal = numba.core.types.Literal
    assert any(isinstance(a, literal) for args in pick.signatures for a in args)
    assert exported_signatures(pick) == [(numba.float64, numba.boolean)]
