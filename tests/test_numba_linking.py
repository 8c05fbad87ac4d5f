"""Kernels loaded from numba's cache keep bitcode, not parsed IR, and still link into new kernels
(granite/_numba_linking.py)."""

import subprocess
import sys
import textwrap

import pytest

KERNEL_MODULE = textwrap.dedent(
    """
    import numba
    import numpy as np

    @numba.njit(cache=True)
    def affine(x):
        return 2.0 * x + np.sqrt(x)
    """
)

FIRST_RUN = textwrap.dedent(
    """
    import granite
    import cached_kernel
    print(cached_kernel.affine(4.0))
    """
)

SECOND_RUN = textwrap.dedent(
    """
    import {first}
    import {second}
    import numba
    import cached_kernel

    assert cached_kernel.affine(4.0) == 10.0
    (library,) = [r.library for r in cached_kernel.affine.overloads.values()]
    assert cached_kernel.affine.stats.cache_hits, "the kernel was not loaded from the cache"
    assert library._shared_module is None, "the parsed IR of a cache-loaded kernel was kept"

    @numba.njit  # not cached: compiling it links the cache-loaded kernel's IR
    def caller(x):
        return cached_kernel.affine(x) + 1.0

    assert caller(9.0) == 22.0, caller(9.0)
    assert library._shared_module is not None, "linking did not parse the kept bitcode"
    print("ok")
    """
)


def _run(code, tmp_path):
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(tmp_path),
           "GRANITE_NUMBA_CACHE_ROOT": str(tmp_path / "cache"), "HOME": str(tmp_path)}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.parametrize("first, second", [("granite", "numba"), ("numba", "granite")])
def test_a_cache_loaded_kernel_keeps_bitcode_and_links_into_a_new_kernel(tmp_path, first, second):
    """Whether numba was imported before granite or after it."""
    (tmp_path / "cached_kernel.py").write_text(KERNEL_MODULE)
    compiled = _run(FIRST_RUN, tmp_path)
    assert compiled.returncode == 0, compiled.stderr
    assert compiled.stdout.strip() == "10.0"
    second = _run(SECOND_RUN.format(first=first, second=second), tmp_path)
    assert second.returncode == 0, second.stderr
    assert second.stdout.strip() == "ok"
