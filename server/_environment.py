"""Settings read from the environment: checked where a command starts (`badf serve`, `demo`, `bench` refuse a bad
one in a line, before anything starts) and read again where they are used."""

from __future__ import annotations

import os


def cpu_threads_setting() -> int | None:
    """$BADF_CPU_THREADS, the threads the CPU back-end shares its launches over: None where unset or empty; a
    ValueError naming the variable where it is not a whole number of at least 1."""
    value = os.environ.get("BADF_CPU_THREADS", "").strip()
    if not value:
        return None
    try:
        threads = int(value)
    except ValueError:
        raise ValueError(f"BADF_CPU_THREADS must be a whole number of threads, got {value!r}") from None
    if threads < 1:
        raise ValueError(f"BADF_CPU_THREADS must be at least 1, got {threads}")
    return threads
