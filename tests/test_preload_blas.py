"""``maxfs run`` imports scipy.linalg's two BLAS/LAPACK extension modules for numba without the
rest of scipy.linalg (service/runs/local.py: preload_numba_blas); numba's kernels still load and
a later ``import scipy.linalg`` is the whole package. In a fresh interpreter: sys.modules."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import sys
from maxfs.service.runs.local import preload_numba_blas
assert preload_numba_blas()
assert "scipy.linalg" not in sys.modules and "scipy.linalg.cython_blas" in sys.modules
assert not preload_numba_blas()  # once is enough
import numpy as np
from numba import njit
@njit
def dot(a, b):
    return np.dot(a, b)  # numba's BLAS path, through scipy.linalg.cython_blas
a = np.arange(6.0).reshape(2, 3)
assert np.array_equal(dot(a, a.T), a @ a.T)
assert "scipy.linalg" not in sys.modules
import scipy.linalg
assert scipy.linalg.cython_blas is sys.modules["scipy.linalg.cython_blas"]
assert scipy.linalg.cython_lapack is sys.modules["scipy.linalg.cython_lapack"]
assert np.allclose(scipy.linalg.solve(np.eye(2) * 2, np.ones(2)), 0.5)
import scipy.sparse.linalg
print("ok")
"""


def test_preload_numba_blas_then_scipy_linalg():
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"
