"""The ``badf`` command: ``serve``, ``view``, ``demo`` and ``bench``.

Each subcommand imports its component lazily, so a client-only install (``pip install badf``) can still
run ``badf --help`` and gets an actionable message for the parts it lacks.
"""

from badf.cli._main import main

__all__ = ["main"]
