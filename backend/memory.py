"""Giving freed heap memory back to the operating system.

CPython, numpy and GTSAM free their objects into the C allocator, and glibc's allocator keeps
freed chunks inside its heap for reuse: after the merge drops a few million small Python objects
(the local models' points), or GTSAM one part of a bundle adjustment, the process still holds
their pages, and the peak of the next step stacks on top of them.  ``malloc_trim(0)`` returns
every free page to the system.  On a C library without it (macOS, musl) nothing happens.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def return_freed_memory() -> bool:
    """Release the C heap's free pages (glibc); True when the allocator supports it."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
