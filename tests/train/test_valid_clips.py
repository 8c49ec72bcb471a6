"""Issue 56 item 3 (consumers): train, evaluate, upscale and export-dataset read a clip only if its last validation
passed and nothing changed since, or it passes now; a failing clip is one line naming the clip and the failed check,
exit 2. The training cache is keyed by the files' content, not their times."""
from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from tests.conftest import edit_header, edit_manifest, set_args  # noqa: E402
from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.clip import UnsafePathError, buffer_path  # noqa: E402
from gbuffer_export.exr import read_exr, write_exr  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from gbuffer_export.validate.verdict import VERDICT  # noqa: E402
from training.cache import ClipCache  # noqa: E402
from tests.train.test_reliability_train_inputs import SMALL  # noqa: E402  (the smallest FuseSR run)

pytestmark = pytest.mark.torch



@pytest.fixture(scope="module")
def base(tmp_path_factory):
    clip = make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    edit_header(clip, lambda m: m.__setitem__("exposure", {"mode": "fixed", "value": 0.5}))
    return clip


@pytest.fixture
def clip(base, tmp_path):
    return shutil.copytree(base, tmp_path / "c", ignore=shutil.ignore_patterns(".blendsr_cache", VERDICT))


def _rewrite_keeping_times(path, k):
    st = os.stat(path)
    a = read_exr(path, ("R", "G", "B"))
    write_exr(path, {ch: (k * a[..., i]).astype(np.float32) for i, ch in enumerate("RGB")})
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_the_cache_rebuilds_when_an_exr_changes_under_kept_file_times(clip):
    cache = ClipCache(clip).ensure(["lr/radiance"])
    old = cache.read(2, "lr/radiance")
    _rewrite_keeping_times(buffer_path(clip, 2, "lr", "radiance"), 2.0)
    fresh = ClipCache(clip)
    assert fresh.rebuilt and fresh.index["arrays"] == {}
    np.testing.assert_allclose(fresh.ensure(["lr/radiance"]).read(2, "lr/radiance"), 2 * old, rtol=1e-6)
    assert not ClipCache(clip).rebuilt  # nothing changed since: the arrays are reused


def test_the_cache_refuses_an_exr_that_became_a_link(clip):
    ClipCache(clip).ensure(["lr/radiance"])
    exr = buffer_path(clip, 2, "lr", "radiance")
    outside = clip.parent / "outside.exr"
    shutil.copy2(exr, outside)
    exr.unlink()
    exr.symlink_to(outside)
    cache = ClipCache(clip)
    assert cache.rebuilt
    with pytest.raises(UnsafePathError, match="symbolic link"):
        cache.ensure(["lr/radiance"])


def _one_error(capsys) -> str:
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("note: ")]
    assert len(err) == 1, err
    return err[0]


def test_every_consumer_refuses_a_clip_whose_exposure_was_edited(clip, tmp_path, capsys):
    edit_manifest(clip, lambda m: m["exposure"].__setitem__("value", 5.0))  # x10 after rendering
    runs = {
        "train": ["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "run"), "--max-steps", "1",
                  *set_args(SMALL)],
        "evaluate": ["evaluate", "--model", "bilinear", "--data", str(clip), "--json", str(tmp_path / "e.json"),
                     "--no-flip", "--no-progress"],
        "upscale": ["upscale", "--model", "bilinear", "--clip", str(clip), "-o", str(tmp_path / "up"),
                    "--no-progress"],
        "export-dataset": ["export-dataset", str(clip), "--format", "nss", "-o", str(tmp_path / "nss")],
    }
    for name, argv in runs.items():
        assert main(argv) == 2, name
        line = _one_error(capsys)
        assert line.startswith(f"blendsr: error: {clip}: fails validation: ERROR ") and "[manifest-identity]" in line, \
            (name, line)
    assert not (tmp_path / "e.json").exists() and not (tmp_path / "nss").exists()
    assert not list((tmp_path / "up").glob("**/*.exr")) if (tmp_path / "up").exists() else True


def test_a_valid_clip_trains_and_its_verdict_is_reused(clip, tmp_path):
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 0
    assert (clip / VERDICT).is_file()
    assert main(["upscale", "--model", "bilinear", "--clip", str(clip), "-o", str(tmp_path / "up"), "--frames",
                 "1:1", "--no-progress"]) == 0
