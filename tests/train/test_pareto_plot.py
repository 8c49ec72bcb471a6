"""The speed-against-error plot (issue 42, item 6): no label over another, a marker, the legend or the axes' edge,
measured with matplotlib's renderer; the data it shows stated on it (clips, HR size, scale, frames, device,
precision)."""
from __future__ import annotations

from pathlib import Path

import pytest

from gbuffer_export.synthetic import make_synthetic_clip


def _rows(n_extra: int) -> list[dict]:
    base = [("bicubic", 8.3, 13.49), ("demod-bilinear", 7.5, 17.11), ("demod-jbu", 61.4, 17.43),
            ("pretrained:fusesr-l", 326.0, 17.99), ("pretrained:fusesr", 587.0, 18.07),
            ("pretrained:fusesr-fast", 117.0, 17.82), ("pretrained:rdg-s", 84.5, 17.22)]
    rows = [{"model": m, "ms_per_frame": ms, "psnr": p} for m, ms, p in base]
    for k in range(n_extra):  # near-coincident runs of the same models: labels that would print over each other
        m, ms, p = base[k % len(base)]
        rows.append({"model": f"{m} (run{k})", "ms_per_frame": ms * (1.02 + 0.01 * k), "psnr": p + 0.02 * k})
    return rows


def _overlap(a, b) -> bool:
    return not (a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1])


@pytest.mark.parametrize("n_extra", [0, 10])
def test_pareto_labels_never_overlap(tmp_path, n_extra):
    pytest.importorskip("matplotlib")
    from training.bench import BenchData, plot
    rows = _rows(n_extra)
    data = BenchData(["/d/clips/walk-00"], [(160, 88)], 4.0, 2, "cpu (test, 2 threads)", "fp32")
    out = plot(rows, tmp_path / "pareto.png", "cpu", data)
    assert (tmp_path / "pareto.png").stat().st_size > 1000
    boxes = [b for _, b in out["labels"]]
    assert [m for m, _ in out["labels"]] == [r["model"] for r in rows]
    ax = out["axes"]
    for i, b in enumerate(boxes):
        assert ax[0] <= b[0] and b[2] <= ax[2] and ax[1] <= b[1] and b[3] <= ax[3], (rows[i]["model"], b, ax)
        assert not _overlap(b, out["legend"]), rows[i]["model"]
        for j in range(i + 1, len(boxes)):
            assert not _overlap(b, boxes[j]), (rows[i]["model"], rows[j]["model"])
        for x, y in out["points"]:  # no label covers a marker
            assert not _overlap(b, (x - 2, y - 2, x + 2, y + 2)), rows[i]["model"]


def test_pareto_plot_states_its_data(tmp_path):
    pytest.importorskip("matplotlib")
    from training.bench import BenchData, plot
    clips = [make_synthetic_clip(tmp_path / "ds" / "clips" / f"c{i}", frames=(1, 2), hr_size=(64, 36), scale=4)
             for i in range(2)]
    result = {"scale": 4, "per_frame": [{}] * 4, "device": "cpu (test, 2 threads)",
              "transform": "reinhard-srgb: sRGB_OETF(x / (1 + x))"}
    data = BenchData.of(clips, result, ["bf16"])
    assert data.lines() == ["c0, c1 of ds: HR 64x36, LR 16x9 (x4); 4 frames per model",
                            "cpu (test, 2 threads); bf16; PSNR of the reinhard-srgb tonemap, mean over the frames"]
    out = plot(_rows(0), tmp_path / "p.png", "cpu", data)
    assert out["texts"] == data.lines()
    many = BenchData([f"/x/ds/clips/k{i}" for i in range(5)], [(64, 36), (128, 72)], 2.0, 10, "cuda (H100)",
                     "fp32")
    assert many.lines()[0] == "5 clips of ds (k0, ..., k4): HR 64x36, 128x72, LR 32x18, 64x36 (x2); 10 frames per model"
    assert Path(many.clips[0]).name == "k0"
