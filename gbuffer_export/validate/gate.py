"""The one gate every consumer (``train``, ``evaluate``, ``upscale``, ``preview``, ``export-dataset``) opens a clip
through: ``open_valid_clip`` reads a clip only if its last validation passed and nothing changed since
(``verdict.current_verdict``), or validates it now (``validate_clip(quick=True)``, which records its verdict) and
refuses a failing clip in one line naming the clip and the failed check."""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Iterable

from ..clip import Clip, ClipError, open_clip
from .runner import validate_clip
from .verdict import clip_content_digest, current_verdict

log = logging.getLogger(__name__)

#: Findings no consumer is refused for: planned frames not rendered (yet) and the buffer files of such frames, since
#: every consumer reads the finished frames only (an interrupted shard run exports as one sequence per run of
#: finished frames).
UNFINISHED = ("missing-frame", "incomplete-frame")


def require_valid(path: str | os.PathLike, *, tolerate: Iterable[str] = ()) -> dict:
    """The clip's verdict (validated now when none is current); ClipError naming the clip and its first failed
    check when it fails on a check not in ``tolerate`` (codes a consumer checks itself, in validate's words)."""
    root = Path(path)
    rec, why = current_verdict(root)
    if rec is None:
        log.debug(f"{root}: validating it ({why})")
        report = validate_clip(root, quick=True)
        rec = report.verdict
        if rec is None:  # changed while validated: judge on the report, key on the files as they are now
            rec = {"ok": report.ok, "errors": [{"code": f.code, "line": f.line()} for f in report.errors],
                   "digest": clip_content_digest(root)}
    tolerated = {*tolerate, *UNFINISHED}
    listed = rec.get("errors", [])
    failed = [e for e in listed if e.get("code") not in tolerated]
    if failed or (not rec["ok"] and rec.get("error_count", len(listed)) > len(listed)):
        line = failed[0]["line"] if failed else "failed"
        raise ClipError(f"{root}: fails validation: {line} ('blendsr validate {root}' lists every finding)")
    return rec


def open_valid_clip(path: str | os.PathLike, *, tolerate: Iterable[str] = ()) -> Clip:
    """``open_clip`` for a consumer: the clip only if its last validation passed and nothing changed since, else
    validated now (``require_valid``); ``clip.digest`` is its content key."""
    clip = open_clip(path)  # the reader's own one-line refusals first
    rec = require_valid(path, tolerate=tolerate)
    clip.digest = rec.get("digest")
    return clip


__all__ = ["UNFINISHED", "require_valid", "open_valid_clip"]
