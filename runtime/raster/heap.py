"""Keep freed frame buffers in the process heap (glibc), so the next frame reuses them.

A frame allocates tens of MB of short-lived arrays (the tile lists, the packed records, the
output images: about 28 MB at 100k Gaussians and 800x800). glibc serves blocks that large with
fresh mmap pages by default and returns them on free, so every frame paid for page faults and
zero-filling: 57-66 ms instead of 51 ms for that frame on a 2-core machine. Raising the mmap
and trim thresholds keeps those blocks in the heap for reuse, at the price of holding up to
`TRIM_BYTES` of freed memory.

It is OFF unless NEHAD_KEEP_HEAP=1. It was switched off while a cross-process difference of
1/255 in one pixel was chased; that turned out to be the forward kernel's fused multiply-adds
differing between JIT-compiled and cached code (fixed in kernels.py), not the heap. Making it
the default waits for a quiet re-measurement and a decision on the memory it holds.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

MMAP_BYTES = 32 << 20  # blocks below this come from the heap (glibc's upper limit on 64-bit)
TRIM_BYTES = 512 << 20  # free memory the heap keeps before returning any to the system
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_done = False


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process when NEHAD_KEEP_HEAP=1; False
    where that does not apply (not set, not Linux/glibc)."""
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux") or os.environ.get("NEHAD_KEEP_HEAP", "0") != "1":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others have no mallopt
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_BYTES))
    return _done
