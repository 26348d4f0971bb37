"""Hand the heap's freed memory back to the OS.

glibc keeps memory a process has freed (large numpy temporaries of a table build or an analysis
window included) in its heap, and the resident size of a gateway that runs for months on an
industrial PC grows to its peak. ``malloc_trim(0)`` returns the free pages; elsewhere (musl, macOS,
Windows) this is a no-op.
"""
from __future__ import annotations


def release_heap() -> None:
    """``malloc_trim(0)`` where glibc is the C library; a no-op elsewhere."""
    try:
        import ctypes
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
