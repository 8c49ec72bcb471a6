"""``blendsr``: one command-line tool with subcommands. It only parses arguments and calls the Python API.

Each command module listed in ``COMMANDS`` exposes ``register(subparsers)``, which adds its parser(s) and sets
``func`` (called with the parsed namespace, returning an exit code). Command modules import neither bpy nor torch
at module level, so ``blendsr --help`` is fast and works with any subset of the extras installed.

Exit codes: 0 success, 1 a check failed (e.g. ``validate`` found problems), 2 bad input (one-line error).
"""
from __future__ import annotations

import argparse
import importlib
import sys

#: The visible table of command modules, in the order ``--help`` lists them.
COMMANDS = (
    "gbuffer_export.commands.render",
    "gbuffer_export.commands.dataset",
    "gbuffer_export.commands.validate",
    "gbuffer_export.commands.lut",
    "training.commands",
    "gbuffer_export.commands.bench",
    "gbuffer_export.commands.demo",
)


def import_optional(modname: str):
    """Import a command module; None when the module itself (not one of its dependencies) is absent."""
    try:
        return importlib.import_module(modname)
    except ModuleNotFoundError as exc:
        if exc.name and modname.startswith(exc.name):
            return None
        raise


class UsageError(Exception):
    """Bad input: printed as one line 'blendsr: error: ...' with exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="blendsr",
        description="Render super-resolution training clips from Blender scenes, train and evaluate upscalers.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Run 'blendsr COMMAND --help' for the units and defaults of each command.",
    )
    from gbuffer_export import __version__
    parser.add_argument("--version", action="version", version=f"blendsr {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for modname in COMMANDS:
        mod = import_optional(modname)
        if mod is not None:
            mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    args.own_process = argv is None  # the command line of this process (a command may re-exec it)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("blendsr: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    except (UsageError, ValueError, FileNotFoundError, FileExistsError, NotADirectoryError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"blendsr: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
