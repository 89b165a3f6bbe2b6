"""What a command needs beyond the client, asked before it starts anything: a module that is not installed
is one line naming it and the extra that installs it, with exit status 2, where the command died in a
traceback (`badf demo`, `badf bench`), or after minutes of work (`badf bench accuracy` without matplotlib)."""

from __future__ import annotations

import importlib.util


def not_installed(command: str, module: str, extra: str) -> str:
    return f"{command} needs {module!r}, which is not installed; install it with: pip install 'badf[{extra}]'"


def missing_extra(command: str, modules: tuple[str, ...], extra: str) -> str | None:
    """The line saying which of `modules` is not installed and that `badf[extra]` installs it, or None when
    all are. Nothing is imported: `badf serve --gpus` starts its workers without importing Warp itself."""
    for module in modules:
        if importlib.util.find_spec(module) is None:
            return not_installed(command, module, extra)
    return None
