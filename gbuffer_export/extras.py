"""Optional extras: which modules each extra of ``pyproject.toml`` provides, and the one-line check every CLI command
runs before it starts (``require``), so that a partial install names the extra to install instead of a traceback.

BlendSR is not published on a package index. The hint says what works where BlendSR runs from: in a checkout (the
source tree beside its ``pyproject.toml``) ``pip install '.[train]'`` there; from an installed wheel
``pip install 'blendsr[train]'``, which adds the extra's packages to the installed blendsr (pip finds blendsr itself
installed and fetches only the extra's dependencies). README, "Installing without make".
"""
from __future__ import annotations

import argparse
import importlib.util
import re
from pathlib import Path

from .errors import BlendSRError

#: extra -> the top-level modules it installs (import names), as in pyproject.toml's optional-dependencies.
EXTRAS: dict[str, tuple[str, ...]] = {
    "render": ("bpy", "trimesh", "rtree", "scipy", "embreex"),
    "train": ("torch", "matplotlib", "pytorch_msssim", "flip_evaluator", "safetensors"),
    "export": ("onnx", "onnxruntime"),
    "cluster": ("ray",),
    "video": ("pycvvdp",),  # the cvvdp package (ColorVideoVDP)
}


class MissingExtra(BlendSRError):
    """An optional extra a command needs is not installed (bad input: the CLI prints it as one line, exit 2)."""


def installed(module: str) -> bool:
    """True when ``module`` can be imported (found on the path; not imported, so bpy/torch start nothing), or is
    imported already."""
    import sys
    if sys.modules.get(module) is not None:
        return True
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a blocked module, or one in sys.modules without a spec
        return False


def checkout_root() -> Path | None:
    """The BlendSR source checkout this package runs from (the folder above it holds blendsr's pyproject.toml), or
    None when it runs from an installed wheel."""
    root = Path(__file__).resolve().parents[1]
    try:
        text = (root / "pyproject.toml").read_text(encoding="utf-8")
    except OSError:
        return None
    return root if re.search(r'^name\s*=\s*"blendsr"', text, re.MULTILINE) else None


def install_hint(extra: str) -> str:
    """The pip command that installs ``extra`` for this installation (see module doc)."""
    root = checkout_root()
    if root is None:
        return f"install the [{extra}] extra: pip install 'blendsr[{extra}]' (adds it to the installed blendsr)"
    try:
        here = Path.cwd().resolve() == root
    except OSError:
        here = False
    return f"install the [{extra}] extra: pip install '.[{extra}]'" + ("" if here else f" in {root}")


def extra_of(module: str) -> str | None:
    """The extra that installs the top-level module ``module`` (None: not an extra's)."""
    top = module.split(".")[0]
    return next((e for e, mods in EXTRAS.items() if top in mods), None)


def require(what: str, *extras: str, modules: tuple[str, ...] | None = None) -> None:
    """Raise MissingExtra naming the first extra (of ``extras``, in order) with a module that is not installed.

    ``what`` names the command in the message ("blendsr train"); ``modules`` restricts the check to these modules
    (default: every module of each extra), e.g. ``require("blendsr bench brdf", "train", modules=("matplotlib",))``.
    """
    for extra in extras:
        mods = EXTRAS[extra] if modules is None else tuple(m for m in modules if extra_of(m) == extra)
        missing = [m for m in mods if not installed(m)]
        if missing:
            are = "is" if len(missing) == 1 else "are"
            raise MissingExtra(f"{what} needs {', '.join(missing)}, which {are} not installed: {install_hint(extra)}")


def missing_module_message(exc: ModuleNotFoundError) -> str | None:
    """The one-line hint for a ModuleNotFoundError of an extra's module raised inside a command (None: not one)."""
    extra = extra_of(exc.name or "")
    if extra is None:
        return None
    return f"no module named '{exc.name}': {install_hint(extra)}"


#: help text that already states its default: "default: X", "(default X)", "default is X", "defaults to",
#: "%(default)s"
_SAYS_DEFAULT = re.compile(r"\bdefault\s*:|\(default\b|\bdefault is\b|\bdefaults? to\b|%\(default\)",
                           re.IGNORECASE)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's line breaks and shows each option's default exactly once: appended as
    ``(default: X)`` unless the help already says its default, the default is None (nothing to show: the help says
    what omitting the option means) or the option is a flag."""

    def _get_help_string(self, action):
        help = action.help or ""
        if _SAYS_DEFAULT.search(help):
            return help
        if action.default is None or action.default is argparse.SUPPRESS or action.default is False:
            return help
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._HelpAction,
                               argparse._VersionAction)):
            return help
        if action.default == [] or action.default == "":
            return help
        if not action.option_strings and action.nargs not in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return help
        return f"{help} (default: %(default)s)"
