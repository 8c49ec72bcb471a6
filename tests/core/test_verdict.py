"""Issue 56 item 3 (numpy side): ``validate`` records its verdict in the clip (pass/fail, the manifest's identity,
every file's BLAKE2b-128 hash), and ``open_valid_clip``, the gate every consumer opens clips through, reads a clip
only while that verdict passed and still describes it (else validates it now) and refuses a failing clip in one line
naming the clip and the failed check."""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from tests.conftest import edit_header, edit_manifest
from gbuffer_export.clip import ClipError, buffer_path
from gbuffer_export.conventions import BUFFERS
from gbuffer_export.exr import read_exr, write_exr
from gbuffer_export.synthetic import make_synthetic_clip
from gbuffer_export.validate import validate_clip
from gbuffer_export.validate.gate import open_valid_clip
from gbuffer_export.validate.verdict import HASH_ALGORITHM, VERDICT, current_verdict, file_hash


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("base") / "clip", frames=(1, 2, 3), hr_size=(64, 36), scale=4)


@pytest.fixture
def clip(base, tmp_path):
    return shutil.copytree(base, tmp_path / "clip", ignore=shutil.ignore_patterns(VERDICT))


def _rewrite_keeping_times(path, fn):
    """Rewrite an EXR's pixels with ``fn`` and put its access and modification times back."""
    st = os.stat(path)
    name = path.parent.name
    a = read_exr(path, BUFFERS[name].channels)
    write_exr(path, {ch: fn(a)[..., i] for i, ch in enumerate(BUFFERS[name].channels)})
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(path).st_mtime_ns == st.st_mtime_ns


def test_validate_records_its_verdict_with_every_files_hash(clip):
    rep = validate_clip(clip)
    assert rep.ok
    rec = json.loads((clip / VERDICT).read_text())
    assert rec["ok"] and rec["hash"] == HASH_ALGORITHM == "blake2b-128" and not rec["quick"]
    assert rec["identity"] == json.loads((clip / "manifest.json").read_text())["identity"]
    exr = buffer_path(clip, 2, "hr", "radiance")
    assert rec["files"]["hr/radiance/000002.exr"]["hash"] == file_hash(exr)
    assert {"manifest.json", "frames/000003.json", "lr/depth/000001.exr"} <= set(rec["files"])
    assert current_verdict(clip) == (rec, "")
    assert rep.stats["verdict"]["digest"] == rec["digest"]
    assert not list(clip.glob(".*.tmp*"))  # written atomically


def test_a_partial_validation_records_nothing(clip):
    validate_clip(clip, frames=[2])
    assert not (clip / VERDICT).exists()


def test_new_bytes_under_kept_file_times_make_the_verdict_stale(clip):
    validate_clip(clip)
    _rewrite_keeping_times(buffer_path(clip, 2, "hr", "radiance"), lambda a: a * np.float32(1e-5))
    rec, why = current_verdict(clip)
    assert rec is None and why == "hr/radiance/000002.exr changed since its last validation"


def test_a_good_clip_opens_and_is_validated_once(clip):
    c = open_valid_clip(clip)  # no verdict yet: validated now (quick), recorded
    rec = json.loads((clip / VERDICT).read_text())
    assert rec["ok"] and rec["quick"] and c.digest == rec["digest"]
    assert open_valid_clip(clip).digest == c.digest
    assert json.loads((clip / VERDICT).read_text())["validated"] == rec["validated"]  # trusted, not re-validated


def _linked_exr(clip):
    exr = buffer_path(clip, 3, "hr", "albedo")
    outside = clip.parent / "albedo.exr"
    shutil.copyfile(exr, outside)
    exr.unlink()
    exr.symlink_to(outside)


def _scale_radiance(clip, k):
    for f in (1, 2, 3):
        _rewrite_keeping_times(buffer_path(clip, f, "hr", "radiance"), lambda a: a * np.float32(k))


#: case -> (corruption after rendering, the check that refuses it); the clip was rendered at a fixed exposure of 0.5
CASES = {
    "exposure x10": (lambda c: edit_manifest(c, lambda m: m["exposure"].__setitem__("value", 5.0)),
                     "manifest-identity"),
    "exposure 1e6": (lambda c: edit_manifest(c, lambda m: m["exposure"].__setitem__("value", 1e6)),
                     "manifest-identity"),
    "exposure nulled": (lambda c: edit_manifest(c, lambda m: m.__setitem__("exposure", None)), "manifest-identity"),
    "exposure deleted": (lambda c: edit_manifest(c, lambda m: m.pop("exposure")), "manifest-identity"),
    "radiance x1e-5": (lambda c: _scale_radiance(c, 1e-5), "dark-frame"),
    "linked EXR": (_linked_exr, "unsafe-link"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_clip_that_fails_validation_is_refused_in_one_line(clip, case):
    corrupt, check = CASES[case]
    edit_header(clip, lambda m: m.__setitem__("exposure", {"mode": "fixed", "value": 0.5}))
    assert open_valid_clip(clip).exposure == 0.5  # it passes, and its verdict is recorded
    corrupt(clip)
    with pytest.raises(ClipError) as exc:
        open_valid_clip(clip)
    line = str(exc.value)
    assert line.startswith(f"{clip}: fails validation: ERROR ") and f"[{check}]" in line and "\n" not in line, line
    assert not json.loads((clip / VERDICT).read_text())["ok"]  # the verdict recorded is the failure
    with pytest.raises(ClipError, match=r"\[" + check + r"\]"):
        open_valid_clip(clip)  # and it stands while nothing changes


def test_a_tolerated_check_is_left_to_the_consumer(clip):
    a = buffer_path(clip, 3, "hr", "radiance")
    _rewrite_keeping_times(a, lambda x: np.where(np.arange(x.shape[1])[None, :, None] == 5, np.nan, x)
                           .astype(np.float32))
    with pytest.raises(ClipError, match=r"\[non-finite\]"):
        open_valid_clip(clip)
    assert open_valid_clip(clip, tolerate=("non-finite",)).digest
