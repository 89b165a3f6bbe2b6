from __future__ import annotations

import argparse
import importlib
import sys

from badf.cli._extras import not_installed

# subcommand -> (module that provides `add_arguments(parser)` and `run(args) -> int`, extra that installs it)
_SUBCOMMANDS: dict[str, tuple[str, str, str]] = {
    "serve": ("badf.server._cli", "server", "run a distance-field worker (and, by default, the Zenoh router)"),
    "view": ("badf.web_viewer._cli", "viewer", "open the web viewer on the workers' objects"),
    "demo": ("badf.server._demo", "all", "worker + streaming client + viewer on an embedded default"),
    "bench": ("badf.bench._cli", "bench", "benchmarks: accuracy against run time, service round trips"),
}

# the subcommands that may run the engine, whose environment settings are checked before they start
_RUN_THE_ENGINE = ("serve", "demo", "bench")


def _load(name: str):
    module_name, extra, _ = _SUBCOMMANDS[name]
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        missing = error.name or "a dependency"
        if missing.startswith("badf."):
            raise SystemExit(f"badf {name}: not built yet ({module_name} is missing)") from None
        print(not_installed(f"badf {name}", missing, extra), file=sys.stderr)
        raise SystemExit(2) from None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="badf",
        description="badf: adaptive distance fields of deforming meshes on the GPU, served over Zenoh.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, _, help_text) in _SUBCOMMANDS.items():
        commands.add_parser(name, help=help_text, add_help=False)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in _SUBCOMMANDS:
        args = parser.parse_args(argv)  # prints help or the error for an unknown command
        parser.print_help()
        return 0 if not argv or argv[0] in ("-h", "--help") else 2
    name, rest = argv[0], argv[1:]
    module = _load(name)
    sub = argparse.ArgumentParser(prog=f"badf {name}", description=_SUBCOMMANDS[name][2])
    module.add_arguments(sub)
    args = sub.parse_args(rest)
    if name in _RUN_THE_ENGINE:
        from badf.server._environment import cpu_threads_setting

        try:
            cpu_threads_setting()
        except ValueError as error:  # one line before anything starts, not a worker's traceback later
            print(f"badf {name}: {error}", file=sys.stderr)
            return 2
    return int(module.run(args) or 0)
