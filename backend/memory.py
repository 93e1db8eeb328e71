"""The machine's memory: how much it has and has free, and giving freed heap memory back to the
operating system.

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
import os


def physical_memory_bytes() -> int | None:
    """The machine's physical memory in bytes (POSIX ``sysconf``); None where it is unknown."""
    try:
        pages, page_size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None
    return int(pages) * int(page_size) if pages > 0 and page_size > 0 else None


def available_memory() -> int | None:
    """Bytes of memory available to new processes (Linux ``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


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
