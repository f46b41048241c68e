"""One BLAS thread for numpy and scipy while the model doctor runs (`tnn_dsl.diagnose`).

The fits' linear algebra is small (a Jacobian of 14 401 rows by 15 columns times itself, a 15 × 15 solve) and
comes between short compiled simulations. OpenBLAS, numpy's and scipy's BLAS, starts its own threads for such a
product and lets them spin while they wait for the next one, on the cores JAX's simulations and a second candidate
fit need: the case study's diagnosis (``python benchmarks/profile_diagnose.py``, one candidate fit at a time, 2
cores) used 172 % CPU and took 99 s; with one BLAS thread 127 % and 86 s, the same finding to the digit
(2026-11-28). The fleet's Ray workers already ran with ``OPENBLAS_NUM_THREADS=1``.

:func:`one_blas_thread` limits every BLAS library loaded in this process to one thread for the duration of a
``with`` block and restores the user's setting after it (``threadpoolctl``, which knows OpenBLAS, MKL and BLIS);
scipy's own OpenBLAS is loaded first so that it is limited too.
"""

from __future__ import annotations

import contextlib
from typing import Iterator


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Inside the block, numpy's and scipy's BLAS use one thread; the previous numbers are restored after it."""
    import scipy.linalg  # noqa: F401  (scipy's OpenBLAS loaded, so that the limit reaches it)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield
