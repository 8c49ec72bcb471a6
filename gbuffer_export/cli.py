"""``blendsr``: one command-line tool with subcommands. It only parses arguments and calls the Python API.

Commands come from the entry-point group ``blendsr.commands`` (``pyproject.toml``): each entry names a module that
exposes ``register(subparsers)``, which adds its parser(s) and sets ``func`` (called with the parsed namespace,
returning an exit code). The core ships render, dataset, validate, lut, bench and demo; the torch layer adds
train, evaluate, upscale and export from its own entry; another package adds commands the same way without touching
this file. ``blendsr bench`` reads the group ``blendsr.bench`` likewise (modules with ``add_arguments(parser)`` and
``run(args)``). Command modules import neither bpy nor torch at module level, so ``blendsr --help`` is fast and
lists every command with any subset of the extras installed; each command checks the extras it needs when it runs
(``gbuffer_export.extras.require``) and names the one to install in one line (exit 2). A module whose own import
fails for lack of an extra's module (another package's command importing torch at module level) is listed as a
command that says which extra to install.

Notes of the library (``logging``) go to stderr as plain lines: INFO and above by default, ``-q`` WARNING and above,
``-v`` DEBUG too (``gbuffer_export.logs``); both go before the command (``blendsr -q render ...``).

Exit codes: 0 success, 1 a check failed (e.g. ``validate`` found problems), 2 bad input (one-line error), 130
interrupted, 70 an internal error (a bug in BlendSR: the traceback, then one line asking to report it).

The error boundary (``main``): bad input is ``gbuffer_export.errors.BlendSRError`` (every typed error of BlendSR
subclasses it), a missing/existing/not-a-folder path, a file that does not parse (JSON, TOML, text encoding) and a
filesystem fault (read-only file system, no space left, permission denied, quota): one line
``blendsr: error: PATH: read-only file system`` and exit 2. Anything else is a bug and says so.
"""
from __future__ import annotations

import os
import signal
import sys


def _interrupted_while_loading(signum, frame):
    """Ctrl-C before ``main`` runs (Python still importing BlendSR): one line and exit 130, no traceback."""
    sys.stderr.write("blendsr: interrupted\n")
    raise SystemExit(130)


# Only as the program (the console script or ``python -m``), never when a library user or a test imports this module.
if __name__ == "__main__" or os.path.basename(sys.argv[0] if sys.argv else "") in ("blendsr", "blendsr.exe"):
    try:
        signal.signal(signal.SIGINT, _interrupted_while_loading)
    except ValueError:  # not the main thread
        pass

import argparse  # noqa: E402
import importlib  # noqa: E402
import traceback  # noqa: E402
from importlib import metadata  # noqa: E402

from .errors import EXIT_INTERNAL, FILESYSTEM_ERRNOS, BlendSRError, bad_input_line, first_line  # noqa: F401

#: The core's own commands, in the order ``--help`` lists them (used as is when blendsr's metadata is not
#: installed, e.g. a source tree on PYTHONPATH); commands of other packages follow in name order.
CORE_COMMANDS = {
    "render": "gbuffer_export.commands.render",
    "dataset": "gbuffer_export.commands.dataset",
    "validate": "gbuffer_export.commands.validate",
    "preview": "gbuffer_export.commands.preview",
    "lut": "gbuffer_export.commands.lut",
    "bench": "gbuffer_export.commands.bench",
    "demo": "gbuffer_export.commands.demo",
    "export-dataset": "gbuffer_export.commands.export_dataset",  # also registers import-nss
}


def entry_modules(group: str, core: dict[str, str] | None = None) -> dict[str, str]:
    """name -> module of the entry-point ``group``: the core's first (in their order), then the others by name."""
    found = {ep.name: ep.value.split(":")[0] for ep in metadata.entry_points(group=group)}
    core = dict(core or {})
    return {**{k: found.get(k, v) for k, v in core.items()}, **{k: found[k] for k in sorted(found) if k not in core}}


def import_optional(modname: str):
    """Import a command module; None when the module itself (not one of its dependencies) is absent; a
    ``MissingModule`` (with the ModuleNotFoundError) when it needs an optional extra's module that is not installed."""
    from .extras import extra_of
    try:
        return importlib.import_module(modname)
    except ModuleNotFoundError as exc:
        if exc.name and (modname == exc.name or modname.startswith(exc.name + ".")):
            return None
        if exc.name and extra_of(exc.name):
            return MissingModule(modname, exc)
        raise


class MissingModule:
    """Stands for a command module that cannot be imported for lack of an extra: ``add_stub`` registers a command
    under the entry's name that accepts any arguments and fails with the one-line hint."""

    def __init__(self, modname: str, exc: ModuleNotFoundError):
        self.modname, self.exc = modname, exc

    def add_stub(self, sub, name: str) -> None:
        from .extras import MissingExtra, missing_module_message
        msg = f"blendsr {name}: {missing_module_message(self.exc)}"
        p = sub.add_parser(name, help=f"(not available: {msg.split(': ', 1)[1]})", add_help=False,
                           prefix_chars="\0")  # every argument (even -h) is taken, so that running it fails
        p.add_argument("args", nargs="*")

        def fail(args):
            raise MissingExtra(msg)
        p.set_defaults(func=fail)


class UsageError(BlendSRError):
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
    noise = parser.add_mutually_exclusive_group()
    noise.add_argument("-q", "--quiet", dest="verbosity", action="store_const", const=-1, default=0,
                       help="show warnings and errors only (no notes; progress bars are unchanged)")
    noise.add_argument("-v", "--verbose", dest="verbosity", action="store_const", const=1,
                       help="also show debug notes")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    seen = set()
    for name, modname in entry_modules("blendsr.commands", CORE_COMMANDS).items():
        if modname in seen:  # one module may register several commands
            continue
        seen.add(modname)
        mod = import_optional(modname)
        if isinstance(mod, MissingModule):
            mod.add_stub(sub, name)
        elif mod is not None:
            mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if signal.getsignal(signal.SIGINT) is _interrupted_while_loading:  # loaded: Ctrl-C is KeyboardInterrupt again
            signal.signal(signal.SIGINT, signal.default_int_handler)
    except KeyboardInterrupt:  # Ctrl-C while the command modules load: nothing started yet
        print("blendsr: interrupted", file=sys.stderr)
        return 130
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    args.own_process = argv is None  # the command line of this process (a command may re-exec it)
    from .logs import stderr_logging
    try:
        with stderr_logging(getattr(args, "verbosity", 0)):  # the library's notes: logging, plain lines on stderr
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("blendsr: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    except BrokenPipeError:  # stdout closed early (`blendsr dataset --dry-run | head`): stop quietly, as cat does
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit's flush writes nowhere
        return 141
    except Exception as exc:  # noqa: BLE001 - the one error boundary of the CLI
        from .extras import missing_module_message
        # an extra's module imported late inside a command names the extra; other bad input is typed
        line = (missing_module_message(exc) if isinstance(exc, ModuleNotFoundError) else None) or bad_input_line(exc)
        if line is None:
            traceback.print_exc()
            print(f"blendsr: internal error (a bug, please report it with the traceback above): "
                  f"{type(exc).__name__}: {first_line(exc)}", file=sys.stderr)
            return EXIT_INTERNAL
        print(f"blendsr: error: {line}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
