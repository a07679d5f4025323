"""glibc malloc settings for a per-frame vision pipeline (a process-wide choice, made by the entry points).

Every frame allocates the same few large buffers (descriptor map, pyramid, GFTT images), which glibc
would ``mmap`` and ``munmap`` anew each frame, page-faulting them in again; raising the mmap and trim
thresholds keeps them on the heap for the next frame to reuse, at the price of memory the process keeps.

The library never calls this on import; ``tracker``, ``nsflow-bench`` and the offline tools do.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

__all__ = ["keep_large_buffers"]

# mallopt parameter numbers from glibc's malloc.h
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

MIB = 1 << 20


def keep_large_buffers(
    mmap_threshold: int = 32 * MIB, trim_threshold: int = 64 * MIB, top_pad: int = 16 * MIB
) -> bool:
    """Keep allocations below ``mmap_threshold`` on the heap and the heap from shrinking below the trim.

    Args:
        mmap_threshold: requests at least this large still get their own mmap. 32 MiB (glibc's own
            ceiling for its adaptive threshold on 64-bit) is above every per-frame buffer of a 752x480
            pipeline.
        trim_threshold: free memory at the top of the heap kept before glibc returns it to the system.
        top_pad: extra bytes requested from the system whenever the heap grows.

    Returns:
        True when glibc accepted all three settings; False on other C libraries (musl, macOS,
        Windows), where nothing is changed.
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    settings = (
        (_M_MMAP_THRESHOLD, mmap_threshold),
        (_M_TRIM_THRESHOLD, trim_threshold),
        (_M_TOP_PAD, top_pad),
    )
    return all(mallopt(param, int(value)) == 1 for param, value in settings)
