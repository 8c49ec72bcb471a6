"""Pictures that explain themselves (issue 31, item 8): the contact sheet's legend and ranges, the side-by-side's
titles in strips of their own and its crops at full resolution."""
from __future__ import annotations

import numpy as np
import pytest

from gbuffer_export import preview


def test_contact_sheet_has_a_legend_and_ranges(tmp_path):
    from PIL import Image

    from gbuffer_export.clip import open_clip
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=(1,), hr_size=(64, 36), scale=4))
    plain = np.asarray(Image.open(preview.contact_sheet(clip, tmp_path / "a.png", legend=False)))
    sheet = np.asarray(Image.open(preview.contact_sheet(clip, tmp_path / "b.png")))
    assert sheet.shape[1] == plain.shape[1] and sheet.shape[0] == plain.shape[0] + 46
    assert np.array_equal(sheet[:plain.shape[0]], plain)
    legend = sheet[plain.shape[0]:]
    for _, _, colour, _ in preview.FLAG_COLOURS:  # every flag colour has a swatch
        want = np.array([int(255 * c) for c in colour])
        assert (np.abs(legend[..., :3].astype(int) - want).max(axis=-1) == 0).sum() >= 50, colour
    depth = clip.read(1, "hr/depth")
    near, far = preview.depth_range(depth)
    assert preview.tile_label("hr/depth", depth) == f"hr/depth {near:.3g}-{far:.3g}"
    assert preview.tile_label("hr/motion", clip.read(1, "hr/motion")).startswith("hr/motion <=")


def test_depth_range_is_what_depth_rgb_shows():
    d = np.linspace(1.0, 10.0, 1000).reshape(10, 100, 1)
    d[0, 0] = np.inf
    near, far = preview.depth_range(d)
    img = preview.depth_rgb(d)
    assert img[0, 0].max() == 0.0  # background black
    i_near = np.unravel_index(np.argmin(np.abs(d[..., 0] - near)), d.shape[:2])
    i_far = np.unravel_index(np.argmin(np.abs(d[..., 0] - far)), d.shape[:2])
    assert img[i_near][0] > 0.99 and img[i_far][0] < 0.01


def test_comparison_sheet_titles_never_clip_and_crops_are_full_resolution():
    rng = np.random.default_rng(0)
    h, w = 36, 64
    ref = rng.random((h, w, 3))
    other = ref.copy()
    other[20:30, 40:60] = 0.0  # where they differ
    panels = [(["a model with a long name that wraps", "PSNR 12.34 dB"], other), (["ground truth"], ref)]
    img = preview.comparison_sheet(panels, zoom=2, notes=["a note"])
    x, y, cw, ch = preview.most_different_window([other, ref], (w // 2, h // 2))
    assert x <= 40 and x + cw >= 56 and y <= 20 and y + ch >= 26
    # the crop row holds the reference's crop, each pixel 2x2, below the titles and the whole frames
    crop = np.repeat(np.repeat(ref[y:y + ch, x:x + cw], 2, 0), 2, 1)
    crop8 = (crop * 255 + 0.5).astype(np.uint8)
    big = (img * 255 + 0.5).astype(np.uint8)
    found = [(r, c) for r in range(big.shape[0] - crop8.shape[0] + 1) for c in (6 + 1 * (w + 6),)
             if np.array_equal(big[r:r + crop8.shape[0], c:c + crop8.shape[1]], crop8)]
    assert found, "the crop of the last panel at 2x is in the picture"
    # the whole frames start below a title strip of their own: two lines, the long one wrapped into a third
    frame_top = found[0][0] - 12 - 6 - h
    assert frame_top >= 6 + 12 * 3
    full = big[frame_top:frame_top + h, 6 + w + 6:6 + 2 * w + 6]
    inner = (slice(1, -1), slice(1, -1))  # inside the crop outline
    same = full[inner] == (ref * 255 + 0.5).astype(np.uint8)[inner]
    assert same.all(axis=-1).mean() > 0.7  # the frame itself (less the outline of the crop), no text over it


@pytest.mark.torch
def test_side_by_side_explains_bicubic(tmp_path):
    pytest.importorskip("torch")
    from PIL import Image

    from gbuffer_export.synthetic import make_synthetic_clip
    from training.demo import side_by_side
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    out = side_by_side("bicubic", str(clip), tmp_path / "s.png", "bicubic again")
    img = np.asarray(Image.open(out))
    assert img.shape[1] == 5 * (64 + 6) + 6  # five panels at full resolution
    assert img.shape[0] > 12 * 2 + 36 + 36 + 12 * 3  # titles, frames, 2x crops, notes
