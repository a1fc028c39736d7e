"""numba compilation of positioning's few hot loops: the step profiles and their layouts
(corner refinement, edge alignment), the edge line fits, the projection with its Jacobian;
and of the synthetic camera's room pass (``fakes.render._room_coordinates``, ``exact``).

A loop that numpy can only do as dozens of small array operations is written once as
plain Python over arrays and compiled here: cached on disk (``__pycache__`` beside its
module, or ``NUMBA_CACHE_DIR`` where the package folder is read-only, as under systemd;
with no writable folder it compiles in every process and warns). Compiling takes ~1-3 s a
kernel and holds the GIL, loading one from the cache ~0.1 s after numba's own ~0.6 s
import, so each kernel comes with a warm-up call on tiny arrays of the types real use
passes, ``warm_up()`` runs them all, ``TargetObserver`` calls it when it is built, and no
frame pays for it; commands without poses never import numba.

Floating-point reordering and fused multiply-adds are allowed, not fastmath's NaN and
infinity assumptions: the step profiles run ~1.3x faster, the positions the same within
1e-13 samples.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable

FASTMATH = {"contract", "reassoc", "arcp", "nsz"}
KERNELS: list[tuple[Callable[[], Callable], Callable[[], object]]] = []  # (kernel, its warm-up), by import


def compiled(function: Callable, warm_up: Callable[[], object], exact: bool = False) -> Callable[[], Callable]:
    """A function returning ``function`` compiled (once a process: compiled or loaded from
    the disk cache on the first call). ``warm_up()`` runs the kernel once on tiny inputs
    through its module's own wrapper, so with the argument types of real use (another
    signature would compile again, on a live frame). ``exact``: IEEE arithmetic in the
    written order, and numpy's division (x / 0 is inf or nan, not an exception), for a
    kernel that must give the same bits as the numpy it stands for."""
    options = {"fastmath": False, "error_model": "numpy"} if exact else {"fastmath": FASTMATH}

    @functools.cache
    def kernel():
        import numba  # imported on first use: ~0.6 s

        try:
            return numba.njit(cache=True, nogil=True, **options)(function)
        except RuntimeError as error:  # no writable cache folder
            warnings.warn(f"{function.__module__}.{function.__name__} compiled without a disk cache ({error}); "
                          "set NUMBA_CACHE_DIR to a writable folder to start faster", RuntimeWarning, stacklevel=3)
            return numba.njit(cache=False, nogil=True, **options)(function)

    KERNELS.append((kernel, warm_up))
    return kernel


def read_only(array, dtype=None):
    """``array`` as a C-contiguous, read-only view (of ``dtype``): numba compiles a
    read-only and a writable array apart, and camera buffers, calibrations and computed
    arrays come both ways; one kind a kernel argument keeps one compiled signature."""
    import numpy as np

    view = np.ascontiguousarray(array, dtype).view()
    view.flags.writeable = False
    return view


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel of the modules imported so far."""
    for _, call in KERNELS:
        call()
