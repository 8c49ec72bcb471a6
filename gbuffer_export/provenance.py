"""Which code made a file: the git commit of the BlendSR checkout that runs, for the records a render writes.

The package version (``__version__``) does not change between commits, and what a clip holds can: the scale set's
val levels rendered on a new machine differ from an earlier render of the same spec and seeds at older code, while a
level clip rendered twice at one commit is bit-identical (issue 54; docs/bench/scaling-families/val-shipped.md).
Each frame record therefore names the commit that rendered it (``commit``, docs/clip-format.md); a render resuming a
clip that other code began logs a warning, and ``blendsr dataset --status`` counts frames per commit.

``source_revision()`` is the commit's 40 hex digits, with ``-dirty`` when a tracked file differs from it (untracked
files are not counted), or None when that is not known: the package does not run from a git checkout that tracks
it (an installed wheel, a copy in another repository's ignored folder), git is missing, refuses the repository
(``safe.directory``), fails or takes over 10 s. git is asked, not parsed by hand (packed refs, worktrees and a
detached HEAD are its business), with the caller's ``GIT_*`` variables removed (a git hook's ``GIT_DIR`` would
point it at another repository), no optional locks (a ``git commit`` beside it is not disturbed) and no console
window on Windows. Asked once per process.
"""
from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
GIT_TIMEOUT_S = 10


def git_env() -> dict[str, str]:
    """The environment git runs in: the caller's without ``GIT_*`` variables, with ``GIT_OPTIONAL_LOCKS=0``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    env["GIT_OPTIONAL_LOCKS"] = "0"
    return env


def _git(where: Path, *args: str) -> str | None:
    """``git -C where ARGS`` output, stripped; None when git fails, is missing or takes over ``GIT_TIMEOUT_S``."""
    flags = getattr(subprocess, "CREATE_NO_WINDOW", 0) if sys.platform == "win32" else 0
    try:
        out = subprocess.run(["git", "-C", str(where), *args], capture_output=True, encoding="utf-8",
                             errors="replace", timeout=GIT_TIMEOUT_S, stdin=subprocess.DEVNULL, env=git_env(),
                             creationflags=flags)
    except (OSError, ValueError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def revision_of(where: Path, tracked: str = "__init__.py") -> str | None:
    """The commit of the checkout holding ``where`` (``-dirty`` when a tracked file is modified), or None when
    ``where/tracked`` is not tracked there or git cannot say (module docstring): no claim rather than a wrong one."""
    if shutil.which("git") is None or _git(where, "ls-files", "--error-unmatch", tracked) is None:
        return None
    head = _git(where, "rev-parse", "HEAD")
    status = _git(where, "status", "--porcelain", "--untracked-files=no")
    if not head or status is None:
        return None
    return head + ("-dirty" if status else "")


@functools.lru_cache(maxsize=1)
def source_revision() -> str | None:
    """The revision of the running ``gbuffer_export`` package (``revision_of`` its folder), once per process."""
    return revision_of(PACKAGE_DIR)


def short_revision(revision: str) -> str:
    """``revision`` for a report line: 12 hex digits, and ``-dirty`` when it is (two renders of one commit, one with
    local changes, are two lines)."""
    return revision[:12] + ("-dirty" if revision.endswith("-dirty") else "")


def other_code(records: dict[int, dict], commit: str | None) -> str | None:
    """What a resumed clip's finished frames say about the code that rendered them, when any names other code than
    ``commit`` (their record's ``commit``; a frame from before the key names none): "frames 1, 2 by 0123456789ab";
    None when every one names ``commit``."""
    other: dict[str, list[int]] = {}
    for f, rec in sorted(records.items()):
        theirs = rec.get("commit") if isinstance(rec, dict) else None
        if theirs != commit:
            other.setdefault(short_revision(theirs) if theirs else "unrecorded code", []).append(f)
    return "; ".join(f"frames {', '.join(map(str, fs))} by {k}" for k, fs in other.items()) or None
