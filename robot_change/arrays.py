"""One array helper the numba kernels' callers share.

A numba kernel is compiled once per argument type, and a read-only array is another type than
a writable one: a reference's depth image (read-only, kept with it) and a current one
(writable) would each cost the kernel a compile on a cold cache.  Callers hand such kernels
:func:`readonly_view` of their arrays, so one compile serves both.
"""

from __future__ import annotations

import numpy as np

__all__ = ["readonly_view"]


def readonly_view(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (no copy; ``a`` itself keeps its flags)."""
    view = a.view()
    view.setflags(write=False)
    return view
