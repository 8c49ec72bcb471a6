"""Pictures that explain themselves (issue 31, item 8; issue 42, item 6): the contact sheet as a grid within a
screen's width, each tile under its buffer, mapping and value range, its legend; the dataset sheet; the
side-by-side's titles in strips of their own and its crops at full resolution."""
from __future__ import annotations

import numpy as np
import pytest

from gbuffer_export import preview


def _disjoint(a, b) -> bool:
    """Two (x, y, w, h) boxes share no pixel."""
    return a[0] + a[2] <= b[0] or b[0] + b[2] <= a[0] or a[1] + a[3] <= b[1] or b[1] + b[3] <= a[1]


def _check_layout(layout, png):
    """Every box inside the sheet, no two of them overlapping, every label line within its column, the PNG the
    size of the layout and each tile's image drawn where the layout puts it (no text over it)."""
    boxes = [b for t in layout.tiles for b in (t.box, t.label_box)]
    for b in boxes:
        assert b[0] >= 0 and b[1] >= 0 and b[0] + b[2] <= layout.width and b[1] + b[3] <= layout.height, b
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert _disjoint(a, b), (a, b)
    for t in layout.tiles:
        assert all(preview.text_width(ln) <= t.col_w for ln in t.lines), t.lines
        x, y, w, h = t.box
        assert np.array_equal(png[y:y + h, x:x + w, :3], preview._u8(t.image)), t.key
    assert png.shape[:2] == (layout.height, layout.width)


def test_contact_sheet_is_a_labelled_grid_within_a_screen(tmp_path):
    from PIL import Image

    from gbuffer_export.clip import open_clip
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=(1, 2), hr_size=(64, 36), scale=4))
    for max_width in (1600, 700):
        layout = preview.contact_sheet_layout(clip, max_width=max_width)
        png = np.asarray(Image.open(preview.contact_sheet(clip, tmp_path / "s.png", max_width=max_width)))
        assert layout.width <= max_width and png.shape[1] == layout.width
        _check_layout(layout, png)
        keys = ["lr/radiance", *(f"hr/{b}" for b in clip.buffers)]
        assert [(t.frame, t.key) for t in layout.tiles] == [(f, k) for f in (1, 2) for k in keys]
        rows = {t.y for t in layout.tiles}
        assert len(rows) >= 2 * 2, "each frame's 13 tiles wrap into rows"
        for t in layout.tiles:
            assert t.lines[0].startswith(t.key) and any(c.isdigit() for c in " ".join(t.lines[1:])), t.lines
    # what the title and the tiles say comes from the clip
    title = " ".join(text for *_, text, _ in layout.texts)
    assert "HR 64x36, LR 16x9 (scale 4)" in title and "exposure x1" in title
    depth = clip.read(1, "hr/depth")
    near, far = preview.depth_range(depth)
    assert layout.tile("hr/depth", 1).lines[1] == f"log: white {near:.3g} (p1) .. black {far:.3g} (p99)"
    assert f"{preview.motion_scale(clip.read(2, 'hr/motion')):.3g} px (p99)" in " ".join(
        layout.tile("hr/motion", 2).lines)


def test_tiles_enlarge_by_whole_factors_and_fit_the_columns():
    assert preview.grid_columns(13, 1600) == (5, 312)  # 6 would fit, 5 gives the same 3 rows
    assert preview.grid_columns(3, 1600) == (3, 525)
    assert preview.tile_size((64, 36), 312) == (256, 144)  # 4x, 82% of the column
    assert preview.tile_size((160, 88), 312) == (312, 172)  # 1x would leave half of it empty
    assert preview.tile_size((1920, 1080), 312) == (312, 176)


def test_material_buffers_are_normalised_and_say_their_range():
    spec = np.full((4, 8, 1), 0.04, np.float32)
    spec[0, 0] = 0.0  # background
    img = preview.visualize("specular", spec)
    assert img[1, 1].min() == 1.0 and img[0, 0].max() == 0.0  # 0.04 is the brightest value: white, not near-black
    want = ["grey: 0 black .. 0.04 white", "min 0 max 0.04 mean 0.0388"]  # 31 of 32 pixels at 0.04
    assert preview.describe("specular", spec) == want
    assert preview.describe("metallic", np.zeros((2, 2, 1))) == ["grey: 0 black .. 0 white", "constant 0"]
    assert preview.visualize("metallic", np.zeros((2, 2, 1))).max() == 0.0
    rough = np.linspace(0.0, 1.6, 9).reshape(3, 3, 1)  # ALPHA pixels may leave [0, 1]: the range says so
    assert preview.describe("roughness", rough)[0] == "grey: 0 black .. 1.6 white"
    assert abs(preview.visualize("roughness", rough)[1, 1, 0] - 0.5) < 1e-9


def test_the_legend_below_the_sheet_shows_what_its_tiles_use(tmp_path):
    from PIL import Image

    from gbuffer_export.clip import open_clip
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=(1,), hr_size=(64, 36), scale=4))
    plain = np.asarray(Image.open(preview.contact_sheet(clip, tmp_path / "a.png", legend=False)))
    sheet = np.asarray(Image.open(preview.contact_sheet(clip, tmp_path / "b.png")))
    legend = preview.legend_strip(plain.shape[1], clip.buffers)
    assert sheet.shape[1] == plain.shape[1] and sheet.shape[0] == plain.shape[0] + legend.shape[0]
    assert np.array_equal(sheet[:plain.shape[0]], plain)
    below = sheet[plain.shape[0]:]
    for _, _, colour, _ in preview.FLAG_COLOURS:  # every flag colour has a swatch
        want = np.array([int(255 * c) for c in colour])
        assert (np.abs(below[..., :3].astype(int) - want).max(axis=-1) == 0).sum() >= 50, colour
    # a narrow sheet wraps its legend instead of cutting it
    assert preview.legend_strip(300, clip.buffers).shape[0] > legend.shape[0]
    # a clip without flags, motion or depth has no legend for them
    assert preview.legend_strip(800, ("radiance", "albedo")).shape[0] < 20


def test_dataset_sheet_puts_several_clips_on_a_row_with_their_labels(tmp_path):
    import json

    from PIL import Image

    from gbuffer_export.dataset.build import INDEX, SCHEMA
    from gbuffer_export.synthetic import make_synthetic_clip
    ds = tmp_path / "ds"
    entries = []
    for i, size in enumerate(((64, 36), (32, 32), (64, 36), (48, 24))):
        make_synthetic_clip(ds / "clips" / f"c{i}", frames=(1, 2), hr_size=size, scale=4)
        entries.append({"id": f"clip-{i}", "path": f"clips/c{i}", "split": ("train", "test")[i % 2],
                        "camera": "walk", "scene_id": f"s{i}", "frames_planned": 2})
    (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "name": "t", "seed": 0,
                                        "splits": {}, "clips": entries}))
    layout = preview.dataset_sheet_layout(ds, 128, max_width=800)
    path, n = preview.dataset_sheet(ds, tmp_path / "s.png", 128, max_width=800)
    assert n == 4 and layout.width <= 800
    _check_layout(layout, np.asarray(Image.open(path)))
    assert len({t.y for t in layout.tiles}) == 2  # two clips (four tiles) per row
    for t in layout.tiles:
        cid = t.lines[0]
        entry = entries[int(cid.split("-")[1])]
        assert t.key == cid and f"{entry['camera']}, {entry['split']}" in t.lines[1]
        assert t.image.shape[1] == 128  # aspect kept: 32x32 is 128 high, 48x24 64
    assert {t.image.shape[0] for t in layout.tiles} == {72, 128, 64}
    assert "4 finished clips" in layout.texts[0][2]
    assert preview.dataset_sheet_layout(ds, 128, ["test"]).tiles[0].key == "clip-1"


def test_depth_range_is_what_depth_rgb_shows_on_a_log_scale():
    d = np.geomspace(1.0, 100.0, 1000).reshape(10, 100, 1)
    d[0, 0] = np.inf
    near, far = preview.depth_range(d)
    assert near == np.percentile(d[np.isfinite(d)], 1) and far == np.percentile(d[np.isfinite(d)], 99)
    img = preview.depth_rgb(d)
    assert img[0, 0].max() == 0.0  # background black
    for depth, grey in ((near, 1.0), (far, 0.0), (np.sqrt(near * far), 0.5)):  # the geometric mean: mid-grey
        i = np.unravel_index(np.argmin(np.abs(d[..., 0] - depth)), d.shape[:2])
        assert abs(img[i][0] - grey) < 0.01, (depth, img[i][0])
    wall = np.full((4, 4, 1), 3.0)
    wall[0] = np.inf
    assert preview.depth_rgb(wall)[1:].min() == 1.0 and preview.depth_rgb(wall)[0].max() == 0.0


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
    from training.commands.demo import side_by_side
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    out = side_by_side("bicubic", str(clip), tmp_path / "s.png", "bicubic again")
    img = np.asarray(Image.open(out))
    assert img.shape[1] == 5 * (64 + 6) + 6  # five panels at full resolution
    assert img.shape[0] > 12 * 2 + 36 + 36 + 12 * 3  # titles, frames, 2x crops, notes
