"""Which code made a file: the git commit of the BlendSR checkout that runs, for the records a render writes.

The package version (``__version__``) does not change between commits, and what a clip holds can: the same spec and
seed rendered a level's camera path differently before and after a change to ``level_cameras`` (issue 54's val
split, re-rendered on a new machine, docs/bench/scaling-families/val-shipped.md). Each frame record therefore names
the commit that rendered it (``source``, docs/clip-format.md), so a clip or dataset resumed across commits says so.

``source_revision()`` is the commit's 40 hex digits, with ``-dirty`` when a tracked file differs from it, or None
when the package does not run from a git checkout that tracks it (an installed wheel, no ``git`` on the PATH).
git is asked, not parsed by hand: packed refs, worktrees and a detached HEAD are its business. Asked once per
process.
"""
from __future__ import annotations

import functools
import shutil
import subprocess
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent


def _git(where: Path, *args: str) -> str | None:
    """``git -C where ARGS`` output, stripped; None when git fails, is missing or takes over 10 s."""
    try:
        out = subprocess.run(["git", "-C", str(where), *args], capture_output=True, text=True, timeout=10,
                             stdin=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def revision_of(where: Path, tracked: str = "__init__.py") -> str | None:
    """The commit of the checkout holding ``where`` (``-dirty`` when a tracked file is modified), or None when
    ``where/tracked`` is not tracked there (a package installed inside some other repository's ignored folder)."""
    if shutil.which("git") is None or _git(where, "ls-files", "--error-unmatch", tracked) is None:
        return None
    head = _git(where, "rev-parse", "HEAD")
    if not head:
        return None
    status = _git(where, "status", "--porcelain", "--untracked-files=no")
    return head + ("-dirty" if status else "")


@functools.lru_cache(maxsize=1)
def source_revision() -> str | None:
    """The revision of the running ``gbuffer_export`` package (``revision_of`` its folder), once per process."""
    return revision_of(PACKAGE_DIR)
