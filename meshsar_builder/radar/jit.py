"""numba for the radar's kernels (echo, facet integral, imaging), and a clear error where it is missing."""

from __future__ import annotations

from meshsar_builder.pipeline.errors import MeshsarError

try:
    from numba import njit
except ImportError as _numba_error:  # a declared dependency: fail when a kernel is asked for
    NUMBA_MISSING = f"the radar needs numba (pip install numba); importing it failed: {_numba_error}"

    def njit(*args, **kwargs):
        def missing(*a, **k):
            raise MeshsarError(NUMBA_MISSING)

        return lambda function: missing
else:
    NUMBA_MISSING = None

# cache=True: numba's on-disk cache numbers a kernel's compiled specialisations in the order each process saves
# them, without a lock (numba#4807). Two processes that compile different specialisations of one kernel at once (a
# fresh checkout under pytest-xdist, a build's workers) can leave the index pointing at the other one's machine
# code, which then runs on arrays of another layout: wrong numbers or a crash, in every later process. So each
# cached kernel is called with one memory layout (the caller makes its arrays contiguous, or passes a whole array
# and an index instead of a strided view); tests/test_jit_cache.py holds every cached kernel to one specialisation.
# fastmath off: no reassociation and no FMA contraction, so sums keep their written order
# and the bytes do not depend on the CPU's instruction set choices beyond IEEE arithmetic.
KERNEL_OPTIONS = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)
