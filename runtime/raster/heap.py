"""Keep freed frame buffers in the process heap (glibc), so the next frame reuses them.

A frame allocates tens of MB of short-lived arrays (the tile lists, the packed records, the
output images: about 28 MB at 100k Gaussians and 800x800). glibc serves blocks that large with
fresh mmap pages by default and returns them on free, so every frame paid for page faults and
zero-filling: 2963 page faults and 47-57 ms per 100k/800x800 frame where the reused heap took
274 faults and 33 ms (docs/performance.md). Raising the mmap and trim thresholds keeps those
blocks in the heap for reuse.

On by default; the bound: blocks of `MMAP_BYTES` (32 MB) and more are still mapped and
returned on free, and the heap returns its free top to the system once more than `TRIM_BYTES`
(128 MB) of it is free, so a process holds about its largest frame's working set (~40 MB for
100k/800x800) between frames. NEHAD_KEEP_HEAP=0 leaves glibc's defaults alone. Frames are
bit-identical either way (the allocator never changes what is computed).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

MMAP_BYTES = 32 << 20  # blocks below this come from the heap (glibc's upper limit on 64-bit)
TRIM_BYTES = 128 << 20  # free top of the heap kept before returning it to the system
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_done = False


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process unless NEHAD_KEEP_HEAP=0; False
    where that does not apply (turned off, not Linux/glibc)."""
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux") or os.environ.get("NEHAD_KEEP_HEAP", "1") == "0":
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
