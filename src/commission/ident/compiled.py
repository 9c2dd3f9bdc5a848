"""How the identifier's per-sample functions are compiled.

numba increments and decrements, atomically, the reference count of every array a function receives
wherever its control flow keeps the array live: a function called at every sample of a record paid
2–3× its arithmetic for them (the Kalman predictor's one-sample prediction: 5 increments and 10
decrements per call). Functions that allocate nothing need no reference counts: :data:`per_sample`
compiles them without the runtime (numba's ``_nrt`` option, where this numba has it; numba refuses to
compile an allocation there, so a function that needs the runtime fails at compile time, not later).
The results are the same bits either way.

A call between compiled functions passes each array as its 7–11 fields (pointer, shape, strides, ...): the
predictor's one-sample prediction, 13 arguments, cost more to call than to compute. :data:`inlined` marks a
function numba copies into its callers instead; a loop compiled with :data:`per_sample` that inlines its
per-sample steps runs as one function, without reference counts (inlined into a function with the runtime,
each array the inlined code names would be counted again). numba compiles every inlined copy again, and
the copies of copies: inline what runs at every sample and keep what runs only at events called (the
compile time grows with the copies; a pass's time does not fall with them).

numba compiles a function once per signature, and an array's signature includes whether it is writable: a
record read from a log, a kept residual and a fresh array would each compile the predictor again (about
3 s a signature, in every process without a cache of it). :func:`read_only` gives the compiled functions
one kind of array.
"""

from __future__ import annotations

import numba.core.cpu
import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

__all__ = ["inlined", "per_sample", "read_only"]

_WITHOUT_RUNTIME = {"_nrt": False} if hasattr(numba.core.cpu.CPUTargetOptions, "_nrt") else {}

#: Decorator of a compiled function that allocates nothing and is called once per sample (or more).
per_sample = njit(cache=True, nogil=True, error_model="numpy", **_WITHOUT_RUNTIME)
#: Decorator of a compiled function that allocates nothing, inlined into the :data:`per_sample` loops that call it.
inlined = njit(cache=True, nogil=True, error_model="numpy", inline="always", **_WITHOUT_RUNTIME)


def read_only(a: ArrayLike, dtype: type = np.float64) -> NDArray:
    """``a`` as a C-contiguous, read-only array of ``dtype``: a read-only view of ``a`` itself where it is
    one already (nothing copied), else of a copy; ``a``'s own flags are left as they were."""
    v = np.ascontiguousarray(a, dtype=dtype).view()
    v.flags.writeable = False
    return v
