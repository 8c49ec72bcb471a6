"""Clip validation (``blendsr validate``): is a clip on disk complete, readable and consistent with the conventions?

Pure numpy + json + OpenEXR (no bpy, no torch). ``validate_clip(path)`` never raises for a broken clip: every
problem becomes a ``Finding`` with a stable ``code`` (see ``CODES``), a severity and a one-line message naming the
file, frame, buffer and the numbers measured. It raises ``ClipError`` only when ``path`` is not a directory.

Checks, in the order ``runner.run`` calls them (one module per family):
    manifest   (``manifest``) loads (JSON, schema, version), header keys, level sizes (hr = lr * scale), buffer
               names; every planned frame finished; ``frames/`` records merged into the manifest; no buffer files
               or torn records of unfinished frames (a half-written clip never passes); leftover temporary files;
    records    (``records``) per frame and level: cameras (4x4 rigid), intrinsics (positive focal), jitter in
               [-0.5, 0.5] px, spp, seed, seconds; hr and lr describe the same camera (lr intrinsics = hr / scale);
    files      (``files``) every buffer of every checked frame at both levels exists, is a readable EXR with the
               level's size, the channels of ``BUFFERS`` and the right sample type (flags uint32);
    values     (``values``) per buffer of a frame and level: finite; depth > 0 on surfaces and +inf exactly on
               background; unit normals on surfaces, zero on background; fbeta in [0, fbeta_max] on surfaces and 1
               on background; material buffers in [0, 1]; emission >= 0; only known flag bits;
    views      (``exposure``) the manifest's exposure; each HR frame, exposed (radiance times the exposure), neither
               practically black nor blown out, its radiance the one its auto exposure was metered on; near and
               far content (HR depth p90/p10) on most frames (a warning); black frames and level cameras in
               ``camera``;
    motion     (``motion``) stored motion against ``reprojection_motion`` on static surface pixels and against the
               rotation-only motion on background pixels (fractions within tolerance); ``motion_next`` the same
               way towards the next camera.
Also: the manifest's ``identity`` is the hash of its header (``manifest-identity``); an HR frame whose depth is finite on
less than 0.5% of its pixels shows nothing (``empty-frame``, in ``camera``). A validation of every frame records its
verdict in the clip (``verdict``: ``CLIP/validation.json``, every file's BLAKE2b-128 hash); consumers open clips
through ``gate.open_valid_clip``, which trusts a current passing verdict or validates the clip itself.
Findings, the report and the run's state are in ``report``, the tolerances in ``options``.
"""
from __future__ import annotations

from .options import ValidationOptions
from .report import CODES, ERROR, WARNING, Finding, ValidationReport
from .runner import validate_clip

__all__ = ["CODES", "ERROR", "WARNING", "Finding", "ValidationOptions", "ValidationReport", "validate_clip"]
