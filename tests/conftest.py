"""Test-session set-up shared by every test module.

OpenBLAS is pinned to one thread before numpy is first imported, as ``granite run`` does
(``granite/cli/main.py``): the last bits of Λ_scaledrift's dense algebra (matrix products,
Cholesky, eigen-solver on the keyframe system) depend on OpenBLAS's thread count, and the
studies of ``tests/test_bench_dask.py`` compare runs made in this process with runs made in
worker processes (which inherit this environment) bit for bit.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
