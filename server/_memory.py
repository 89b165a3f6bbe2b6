"""Handing memory that deleted objects freed back to the system."""

from __future__ import annotations

import ctypes
import functools
import sys
from typing import Callable


def release_freed_memory() -> None:
    """Ask the C library to return freed heap memory to the system (glibc's malloc_trim); nothing elsewhere.

    glibc keeps the pages of freed blocks in its arenas. A worker whose objects came and went (register, a few
    frames, delete, each under a new name) grew by 140 to 190 KB per object on the CPU, linearly, for as long
    as it ran, and stayed flat when malloc_trim ran every 2 s (2026-11-22, eleventh outside check).
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim  # absent from musl
    except (OSError, AttributeError):
        return None
