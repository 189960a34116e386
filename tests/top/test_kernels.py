"""The compiled kernels' cache (``phrt_usd.kernels``): phrt's own directory, named by the
sources, found by every new process, announced when a render is about to compile."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from phrt_usd import kernels


def test_a_changed_source_names_another_cache(monkeypatch, tmp_path):
    """The cache directory hashes every source: an edited kernel, or an edited constant
    a kernel reads from another module, never loads old code."""
    before = kernels.source_hash()
    edited = tmp_path / "surface.py"
    original = kernels._source_path("phrt_usd.model.surface")
    edited.write_bytes(original.read_bytes() + b"\n# edited\n")
    real = kernels._source_path
    monkeypatch.setattr(
        kernels,
        "_source_path",
        lambda name: edited if name == "phrt_usd.model.surface" else real(name),
    )
    assert kernels.source_hash() != before


def test_the_cache_follows_phrt_cache_dir(monkeypatch, tmp_path):
    monkeypatch.setenv(kernels.CACHE_ENV, str(tmp_path / "mine"))
    assert kernels._parent_dir() == tmp_path / "mine"


def test_an_unwritable_cache_dir_falls_back_to_the_temporary_dir(monkeypatch, tmp_path):
    """A read-only home (a container, a locked-down farm node) still caches."""
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    monkeypatch.setenv(kernels.CACHE_ENV, str(blocked / "sub"))
    assert kernels._parent_dir().name == f"phrt-usd-{os.getuid()}"


def test_only_kernel_modules_load():
    with pytest.raises(ValueError):
        kernels.load("phrt_usd.model.surface")


def test_kernels_of_other_code_keep_numba_s_own_cache():
    """The locator takes phrt's kernel modules only."""
    import numba

    @numba.njit(cache=False)
    def other(x):
        return x

    assert kernels._KernelCacheLocator.from_function(other.py_func, __file__) is None


def _python(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300
    )


@pytest.mark.slow
def test_a_new_process_loads_every_kernel_from_the_cache():
    """The suite's session-scoped fixture compiled every kernel; a new process (a render's) finds
    them all in the cache and compiles none (``phrt kernels --check``)."""
    done = subprocess.run(
        [sys.executable, "-m", "phrt_usd.kernels", "--check"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert str(kernels.cache_dir()) in done.stdout
    assert _python("from phrt_usd import kernels; print(kernels.form())", dict(os.environ)
                   ).stdout.strip() == "cached"  # fmt: skip


@pytest.mark.slow
def test_an_empty_cache_is_announced_once(tmp_path):
    """A render about to compile says so in one line on stderr, naming `phrt kernels`;
    loading a module does not compile yet, so this is quick."""
    env = {**os.environ, kernels.CACHE_ENV: str(tmp_path)}
    code = (
        "from phrt_usd import kernels\n"
        "for m in kernels.KERNEL_MODULES: kernels.load(m)\n"
        "print(kernels.form())\n"
    )
    done = _python(code, env)
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if "compiling" in line]
    assert len(lines) == 1 and "phrt kernels" in lines[0], done.stderr
    assert str(tmp_path) in lines[0]
    assert done.stdout.strip() == "compiled"
