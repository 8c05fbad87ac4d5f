"""numba's on-disk cache is keyed by a hash of the package sources, so it is never stale."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

import granite
from granite._numba_cache import PACKAGE_DIR, source_digest


def test_granite_kernels_are_cached_under_the_source_hash():
    from granite.backend.stereographic import bearing_from_stereo

    cache_dir = Path(os.environ["NUMBA_CACHE_DIR"])
    assert cache_dir.name == source_digest()[:16]
    assert Path(granite.__file__).resolve().parent == PACKAGE_DIR
    bearing_from_stereo(np.zeros(2))
    assert Path(bearing_from_stereo.stats.cache_path).is_relative_to(cache_dir)


def _write_toy(root: Path, inner_value: int) -> None:
    """A package whose kernel ``outer`` (in outer.py) calls ``inner`` (in inner.py)."""
    pkg = root / "toy"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text(textwrap.dedent("""
        from pathlib import Path
        from granite._numba_cache import configure_numba_cache
        configure_numba_cache(Path(__file__).resolve().parent)
    """))
    (pkg / "inner.py").write_text(textwrap.dedent(f"""
        import numba
        @numba.njit(cache=True)
        def inner():
            return {inner_value}
    """))
    if (pkg / "outer.py").exists():
        return  # outer.py stays untouched: numba's own stamp of it does not change
    (pkg / "outer.py").write_text(textwrap.dedent("""
        import numba
        from toy.inner import inner
        @numba.njit(cache=True)
        def outer():
            return inner() + 100
    """))


def test_editing_a_called_module_recompiles_the_caller(tmp_path):
    """numba alone would load ``outer`` from its cache after ``inner.py`` changed (outer.py's
    stamp did not change) and print the old value."""
    env = dict(os.environ, PYTHONPATH=f"{tmp_path}{os.pathsep}{PACKAGE_DIR.parent}",
               GRANITE_NUMBA_CACHE_ROOT=str(tmp_path / "cache"))
    env.pop("NUMBA_CACHE_DIR", None)
    code = "import toy.outer; print(toy.outer.outer())"
    results = []
    for value in (1, 2, 2):
        _write_toy(tmp_path, value)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, check=True)
        results.append(int(out.stdout.strip()))
    assert results == [101, 102, 102]
    toy_caches = {p.name for p in (tmp_path / "cache").iterdir()} - {source_digest()[:16]}
    assert len(toy_caches) == 2  # one cache per source version of the toy package


def test_freshly_compiled_and_cached_backend_kernels_give_the_same_bits(tmp_path):
    """The process that compiles the kernels into an empty cache and a later one that loads
    them compute the same window solution bit for bit (fast-math reassociation in
    ``schur_reduce`` broke this: docs/backend.md)."""
    env = dict(os.environ, PYTHONPATH=str(PACKAGE_DIR.parent),
               GRANITE_NUMBA_CACHE_ROOT=str(tmp_path / "cache"), OPENBLAS_NUM_THREADS="1")
    env.pop("NUMBA_CACHE_DIR", None)
    code = textwrap.dedent("""
        import numpy as np
        from granite.backend.synthetic import build_window, make_scene
        win = build_window(make_scene(num_frames=6, num_points=200), pose_noise=(0.05, 0.02),
                           inv_dist_noise=0.1, seed=4)
        win.optimize(max_iterations=3)
        poses = np.stack([win.pose(f) for f in win.frame_ids])
        print(float(np.abs(poses).sum()).hex(), float(win.hessian_blocks().H.sum()).hex())
    """)
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                           timeout=300) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    assert runs[0].stdout.strip() == runs[1].stdout.strip()
    assert any(p.suffix == ".nbi" for p in (tmp_path / "cache").rglob("*"))  # really cached


def test_has_cached_kernels_sees_a_compiled_kernel_only(tmp_path):
    from granite._numba_cache import compile_notice, has_cached_kernels

    code = textwrap.dedent("""
        import os, sys
        from pathlib import Path
        import granite  # points NUMBA_CACHE_DIR at GRANITE_NUMBA_CACHE_ROOT/<hash>
        from granite._numba_cache import compile_notice, has_cached_kernels
        import numba
        @numba.njit(cache=True)
        def twice(x):
            return 2 * x
        @numba.njit(cache=True)
        def thrice(x):
            return 3 * x
        before = has_cached_kernels(), compile_notice("granite run") is not None
        twice(3)
        print(before, (has_cached_kernels(), compile_notice("granite run") is not None),
              (has_cached_kernels(kernels=(twice,)), has_cached_kernels(kernels=(twice, thrice)),
               compile_notice("granite run", (thrice,)) is not None))
        print(os.environ["NUMBA_CACHE_DIR"])
    """)
    script = tmp_path / "compile_one.py"  # numba caches kernels of files only
    script.write_text(code)
    env = {**os.environ, "GRANITE_NUMBA_CACHE_ROOT": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    flags, folder = done.stdout.strip().splitlines()
    assert flags == "(False, True) (True, False) (True, False, True)"
    assert Path(folder).is_relative_to(tmp_path / "cache")
    assert has_cached_kernels(Path(folder)) and not has_cached_kernels(tmp_path / "empty")
