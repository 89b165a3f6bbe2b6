"""Benchmarks: each module prints a table and writes JSON; `badf bench NAME` runs one."""
