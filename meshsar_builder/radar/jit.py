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

# fastmath off: no reassociation and no FMA contraction, so sums keep their written order
# and the bytes do not depend on the CPU's instruction set choices beyond IEEE arithmetic.
KERNEL_OPTIONS = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)
