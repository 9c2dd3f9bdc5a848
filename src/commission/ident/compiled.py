"""How the identifier's per-sample functions are compiled.

numba increments and decrements, atomically, the reference count of every array a function receives
wherever its control flow keeps the array live: a function called at every sample of a record paid
2–3× its arithmetic for them (the Kalman predictor's one-sample prediction: 5 increments and 10
decrements per call). Functions that allocate nothing need no reference counts: :data:`per_sample`
compiles them without the runtime (numba's ``_nrt`` option, where this numba has it; numba refuses to
compile an allocation there, so a function that needs the runtime fails at compile time, not later).
The results are the same bits either way.
"""

from __future__ import annotations

import numba.core.cpu
from numba import njit

__all__ = ["per_sample"]

_WITHOUT_RUNTIME = {"_nrt": False} if hasattr(numba.core.cpu.CPUTargetOptions, "_nrt") else {}

#: Decorator of a compiled function that allocates nothing and is called once per sample (or more).
per_sample = njit(cache=True, nogil=True, error_model="numpy", **_WITHOUT_RUNTIME)
