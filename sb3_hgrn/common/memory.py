"""Freed memory kept for reuse, so that large tensors are not paid for in page faults.

glibc's ``malloc`` serves an allocation above 32 MiB (the most its threshold adapts to) with a fresh
``mmap`` and hands it back to the operating system when it is freed. Every such tensor of a gradient
step (the paper-size network's ``(128 graphs x 100 agents, 1024)`` activations are 52 MB) then
faults in each of its pages again on first touch, which made copying such a tensor several times
slower than copying it into reused memory. :func:`keep_freed_memory` asks ``malloc`` (``mallopt``) to serve
every allocation from its heap and to keep freed memory there, so later steps reuse it. The
process then holds its peak memory until it ends (``docs/results_speed.md`` measures both).

The graph algorithms call it when they start learning on the CPU. It acts only on Linux with glibc;
setting the environment variable ``SB3_HGRN_KEEP_FREED_MEMORY=0`` turns it off.
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform

OPT_OUT_VARIABLE = "SB3_HGRN_KEEP_FREED_MEMORY"
"""Environment variable: ``0`` leaves ``malloc``'s settings alone."""

M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
"""``mallopt`` parameters (glibc's ``malloc.h``)."""

LARGEST_TRIM_THRESHOLD = 2**31 - 1
"""Free memory at the top of the heap is returned to the system only beyond this (an ``int``)."""


@functools.cache
def keep_freed_memory() -> bool:
    """Serve every allocation from ``malloc``'s heap (no ``mmap``: ``M_MMAP_MAX`` 0) and keep freed
    memory there (``M_TRIM_THRESHOLD`` at its largest), once per process.

    :return: whether ``malloc`` took the settings: ``False`` off glibc, or when
        :data:`OPT_OUT_VARIABLE` is ``0``.
    """
    if os.environ.get(OPT_OUT_VARIABLE, "1").strip() == "0" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, LARGEST_TRIM_THRESHOLD))
