"""Per-asset table of models on a dataset split (docs/results.md): PSNR, SSIM and tPSNR per asset (clips of one asset
or one level region grouped), the mean over frames, and each model's PSNR difference to a reference model.

    .venv/bin/python benchmarks/per_asset.py DATASET [--split test] [--models bicubic,demod-jbu,pretrained:fusesr]
        [--reference demod-jbu] [-o OUT.json]

Clips group by the index's ``scene_id``: an asset's name (``SheenChair``), a level region (``garage@cell2-0``) or a
built-in seed (``builtin:36``).
Recurrent models run each clip from its first frame, as ``blendsr evaluate`` does.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("--split", default="test")
    p.add_argument("--models", default="bicubic,demod-bilinear,demod-jbu,pretrained:fusesr,pretrained:fusesr-l")
    p.add_argument("--reference", default="demod-jbu")
    p.add_argument("-o", dest="out", type=Path)
    a = p.parse_args(argv)
    from gbuffer_export.dataset.build import read_index, split_clips
    from training.bench import parse_models
    from training.evaluate import EvalOptions, evaluate_model, group_means
    from training.inference.loading import load_model

    index = read_index(a.dataset)
    group_of = {Path(c["path"]).name: str(c.get("scene_id") or Path(c["path"]).name) for c in index["clips"]}
    clips = [str(c) for c in split_clips(a.dataset, a.split)]
    result = {"dataset": str(a.dataset), "split": a.split, "clips": [Path(c).name for c in clips], "models": {}}
    for label, spec in parse_models(a.models):  # as bench models reads --models (NAME:CHECKPOINT, pretrained:NAME)
        r = evaluate_model(load_model(spec, 4), clips, EvalOptions(flip=False, scale=4))
        per = group_means(r, lambda c: group_of.get(c, c))
        result["models"][label] = {"mean": {k: r["mean"][k] for k in ("psnr", "ssim", "tpsnr")}, "per_asset": per}
        print(f"{label}: PSNR {r['mean']['psnr']:.2f} dB", file=sys.stderr)
    ref = result["models"].get(a.reference)
    assets = sorted({g for m in result["models"].values() for g in m["per_asset"]})
    lines = ["| model | mean PSNR / SSIM / tPSNR | " + " | ".join(assets) + " |",
             "|---|---|" + "---|" * len(assets)]
    for spec, m in result["models"].items():
        cells = []
        for g in assets:
            v = m["per_asset"][g]["psnr"]
            d = f" ({v - ref['per_asset'][g]['psnr']:+.2f})" if ref and spec != a.reference else ""
            cells.append(f"{v:.2f}{d}")
        mean = m["mean"]
        d = f" ({mean['psnr'] - ref['mean']['psnr']:+.2f})" if ref and spec != a.reference else ""
        lines.append(f"| {spec} | {mean['psnr']:.2f}{d} / {mean['ssim']:.4f} / {mean['tpsnr']:.2f} | "
                     + " | ".join(cells) + " |")
    result["table"] = "\n".join(lines)
    print(result["table"])
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
