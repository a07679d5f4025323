"""glibc malloc settings for a per-frame vision pipeline (a process-wide choice, made by the entry points).

Every frame allocates the same few large buffers: the 752x480 d=4 descriptor map (5.8 MB), its pyramid,
OpenCV's GFTT eigenvalue and dilation images (1.4 MB each). glibc serves requests above its mmap
threshold (128 KiB at start, adapting up to 32 MiB) with fresh ``mmap`` pages and returns them with
``munmap`` on free, so each frame page-faults its buffers in again, and in a virtual machine a fault is
expensive. Raising the mmap and trim thresholds keeps those buffers on the heap, where the next frame
reuses them. Measured with ``nsflow-bench`` methods interleaved (752x480, 150 points, 2-core VM), two
runs each way: NSFlow frame 15.4-16.3 -> 14.4-14.7 ms, mostly GFTT (2.3-3.1 -> 1.6 ms); classical frame
5.6-6.4 -> 4.7-4.9 ms. The price is memory the process keeps instead of returning: after the 752x480
benchmark of three methods, the node benchmark's process held 277 MB instead of 182 MB (flat over 10,000
further frames: +0.08 MB, so nothing leaks); a 64 or 256 MiB trim threshold made no difference there.

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
