"""The tests' tolerances; the one table lives in badf.bench._tolerances, where the benchmarks read it too."""

from badf.bench._tolerances import *  # noqa: F401,F403
