"""Model cards of the shipped networks, generated from their weights JSON (no torch).

    make generate            # writes docs/models/cards/<weights file stem>.md
    make generate --check    # exit 1 naming every stale card (tests/train/test_model_cards.py)

A card says what the network is for, what it reads, the data it was trained on (every scene of its dataset spec
with its split, and each third-party scene's licence and attribution as ``../shared/scenes/README.md`` gives them at
generation time), its val and test margins over ``demod-jbu`` as recorded in its JSON (``scores_on_*_split``,
``worst_case_val``), its speed as recorded under docs/bench/, and its limits. Everything comes from files: the
weights JSON (``training/weights/*.json``), the dataset spec it names, the model table, the buffer table
(``gbuffer_export/dataset/model_buffers.json``) and the shared scenes' README; rerun after any of them changes.
"""
from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

from training.models import MODELS
from training.pretrained import PREFIX, PRETRAINED, WEIGHTS_DIR, test_deferred, val_records

REPO = Path(__file__).resolve().parents[2]
CARDS_DIR = REPO / "docs" / "models" / "cards"
SCENES_README = REPO.parent / "shared" / "scenes" / "README.md"
BUFFERS_JSON = REPO / "gbuffer_export" / "dataset" / "model_buffers.json"
#: Speed records (``blendsr bench models`` without --data), GPU first: a model's row in each that has one.
SPEED_RECORDS = ("docs/bench/gpu-h200/speed_compiled.json", "docs/bench/speed-cpu/bench_speed.json",
                 "docs/bench/speed-cpu-networks/bench_speed.json")
BASELINE = "demod-jbu"
#: What a source of each kind is, for the card's data table.
BUILTIN = "BlendSR's built-in procedural courtyard (this repository, MIT)"
BLENDER_HDRI = "Blender's bundled studio-light HDRIs (`builtin:NAME`, shipped inside bpy; not in ../shared)"


def licence_rows(readme: str) -> list[dict]:
    """The rows of the shared scenes' README table: path (without "(and ...)"), licence, attribution."""
    rows = []
    for line in readme.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[0] not in ("Path", "") and not set(cells[0]) <= set("-"):
            rows.append({"path": cells[0].split(" (")[0].strip(), "licence": cells[2], "attribution": cells[3]})
    return rows


def licence_of(rel: str, rows: list[dict]) -> dict | None:
    """The README row of ``rel`` (a path under shared/scenes): the same file, the same file in another format in the
    same folder ("garage.blend (and .gltf)"), or a file inside the folder ``rel`` (an asset folder)."""
    r = Path(rel)
    for row in rows:
        p = Path(row["path"])
        if p == r or (p.parent == r.parent and p.stem == r.stem) or row["path"].startswith(rel.rstrip("/") + "/"):
            return row
    if rel.startswith("hdri"):
        return next((row for row in rows if row["path"].startswith("hdri/")), None)
    return None


def _shared_rel(path: str) -> str | None:
    """The part of a spec path under shared/scenes ("levels/garage/garage.blend"), None for another path."""
    key = "shared/scenes/"
    return path.split(key, 1)[1] if key in path else None


def scenes_of(clips: dict[str, list[str]], spec: dict) -> list[dict]:
    """One row per scene of the clips ({split: clip names}): source, kind, scene file (under shared/scenes, or the
    built-in generator), clip counts per split, HDRIs the source lights with."""
    sources = {s.get("name"): s for s in spec.get("source", [])}
    rows: dict[tuple, dict] = {}
    for split, names in clips.items():
        for clip in names:
            src_name, _, rest = clip.partition("-")
            src = sources.get(src_name, {})
            scene = rest.rsplit("-", 1)[0] if src.get("kind") != "builtin" else "seeds"
            key = (src_name, scene)
            row = rows.setdefault(key, {"source": src_name, "kind": src.get("kind", "not in the spec now"),
                                        "scene": scene, "file": _scene_file(src, scene), "splits": {},
                                        "folders": _asset_folders(src),
                                        "hdri": [h for h in src.get("hdri", []) if isinstance(h, str)]})
            row["splits"][split] = row["splits"].get(split, 0) + 1
    return list(rows.values())


def _asset_folders(src: dict) -> list[str]:
    """The folders under shared/scenes an ``assets`` source scans (none for another kind)."""
    rels = [r for r in map(_shared_rel, src.get("paths", [])) if r is not None]
    return [r for r in rels if src.get("kind") == "assets" and not Path(r).suffix]


def _scene_file(src: dict, scene: str) -> str | None:
    """The scene's path under shared/scenes: the source's file of that stem, or its asset folder of that name (one
    folder; with several, ``asset_row`` finds it in the README)."""
    rels = [r for r in map(_shared_rel, src.get("paths", [])) if r is not None]
    named = [r for r in rels if Path(r).stem == scene or Path(r).name == scene]
    if named:
        return named[0]
    folders = _asset_folders(src)
    return f"{folders[0]}/{scene}" if len(folders) == 1 else None


def asset_row(scene: str, folders: list[str], rows: list[dict]) -> dict | None:
    """The README row of an asset an ``assets`` source over several folders found: a row under one of the folders
    whose path has a folder of the asset's name ("gltf_more/ClearCoatTest/...") or whose file stem is its name
    ("gltf_more/DutchShip/dutch_ship_medium_1k.gltf")."""
    for row in rows:
        p = Path(row["path"])
        for f in folders:
            if p.is_relative_to(f) and (p.relative_to(f).parts[0] == scene or p.stem == scene):
                return row
    return None


def _margin(scores: dict, model: str) -> str:
    """'PSNR P dB, margin +M dB over demod-jbu (smallest per clip +m dB, CLIP), SSIM, tPSNR' of a recorded split."""
    me, base = scores.get(model) or {}, scores.get(BASELINE) or {}
    if not me:
        return "not recorded"
    parts = [f"PSNR {me['psnr']:.2f} dB"]
    if base:
        parts.append(f"margin {me['psnr'] - base['psnr']:+.2f} dB over `{BASELINE}`")
        clips = {c: v - base["per_clip"][c] for c, v in me.get("per_clip", {}).items() if c in base.get("per_clip", {})}
        if clips:
            worst = min(clips, key=clips.get)
            parts.append(f"smallest per clip {clips[worst]:+.2f} dB ({worst})")
    parts += [f"SSIM {me['ssim']:.4f}"] + ([f"tPSNR {me['tpsnr']:.2f} dB"] if me.get("tpsnr") is not None else [])
    parts.append(f"{me.get('frames', '?')} frames")
    return ", ".join(parts)


def speed_lines(model: str, params: int, repo: Path = REPO) -> list[str]:
    """One line per speed record holding ``model``: device, size, variant, ms, MACs per pixel (and a note when the
    record's parameter count is not these weights')."""
    lines = []
    for rel in SPEED_RECORDS:
        try:
            rec = json.loads((repo / rel).read_text())
        except (OSError, ValueError):
            continue
        rows = [r for r in rec.get("rows", []) if r.get("model") == model]
        if not rows:
            continue
        r = min(rows, key=lambda r: r["ms"])
        w, h = rec.get("size", ["?", "?"])
        note = "" if r.get("params") == params else (f"; the record's network had {r.get('params'):,} parameters, "
                                                     f"these weights {params:,}: it predates a change")
        lines.append(f"- {r['ms']:.1f} ms per {w}x{h} frame (x{rec.get('scale')}, batch {rec.get('batch')}, "
                     f"{r['variant']}) on {rec.get('device')}, {r['macs_per_px']:,.0f} multiply-accumulates per "
                     f"output pixel: [{rel}](../../../{rel}){note}")
    if len(lines) > 1:
        lines.append("- Each record is one run of `blendsr bench models` (the CPU ones on a shared 2-core machine, on "
                     "different days): compare networks within one record, not across them.")
    return lines or ["- no speed record under docs/bench holds this network (`blendsr bench models --models "
                     f"{model} --size 1920x1080` measures it)"]


def _data_lines(meta: dict, spec_text: str | None, readme: str | None) -> list[str]:
    """The card's training-data section: the spec, the split sizes and one table row per scene with its licence."""
    import hashlib
    ds = meta["dataset"]
    clips = {s: ds.get(f"{s}_clips", []) for s in ("train", "val", "test")}
    out = [f"Dataset `{ds.get('name')}` from [{ds['spec_file']}](../../../{ds['spec_file']}) (sha256 "
           f"`{ds.get('spec_sha256', '?')[:12]}...`): {len(clips['train'])} train, {len(clips['val'])} val and "
           + ("test clips not read yet (see Margins)" if test_deferred(meta)
              else f"{len(clips['test'])} test clips") + ", split by scene, asset or level region (docs/dataset.md)."]
    if spec_text is None:
        return out + ["", "The spec file is not in this checkout: its sources cannot be listed."]
    if hashlib.sha256(spec_text.encode()).hexdigest() != ds.get("spec_sha256"):
        out += ["", "The spec has changed since these weights were trained: the scenes below are read from "
                    "today's file (a clip whose source it no longer has says so)."]
    rows = licence_rows(readme) if readme is not None else []
    out += ["", "| source (kind) | scene | train / val / test clips | licence | attribution |", "|---|---|---|---|---|"]
    hdris = set()
    for s in scenes_of(clips, tomllib.loads(spec_text)):
        n = "/".join(str(s["splits"].get(k, 0)) for k in ("train", "val", "test"))
        hdris.update(s["hdri"])
        if s["kind"] == "builtin":
            out.append(f"| {s['source']} (builtin) | seeds | {n} | MIT | {BUILTIN} |")
            continue
        lic = licence_of(s["file"], rows) if s["file"] else asset_row(s["scene"], s["folders"], rows)
        where = f"`{s['file'] or lic['path']}`" if s["file"] or lic else s["scene"]
        out.append(f"| {s['source']} ({s['kind']}) | {where} | {n} | "
                   + (f"{lic['licence']} | {lic['attribution']} |" if lic else
                      ("not listed in ../shared/scenes/README.md | |" if readme is not None else
                       "../shared/scenes/README.md absent when generated | |")))
    out += ["", "Environment light (HDRIs) of the generated environments and built-in scenes:"]
    for h in sorted(hdris):
        rel = _shared_rel(h)
        lic = licence_of(rel, rows) if rel else None
        out.append(f"- `{h}`: " + (f"{lic['licence']}, {lic['attribution']}" if lic else BLENDER_HDRI
                                  if h.startswith("builtin:") else "not listed in ../shared/scenes/README.md"))
    return out


def _limit_lines(meta: dict, model: str) -> list[str]:
    """Limits read from the record: scale, margins below the baseline (split means, groups, clips), the val rule."""
    out = []
    scales = "any scale (trained on 2x and 4x)" if model == "fourier-sr" else f"{meta['scale']}x only"
    out.append(f"- Scale: {scales}; trained and scored only on BlendSR's Cycles renders of the spec above.")
    for split in ("val", "test"):
        scores = meta.get(f"scores_on_{split}_split") or {}
        me, base = scores.get(model) or {}, scores.get(BASELINE) or {}
        below = sorted(c for c, v in me.get("per_clip", {}).items() if v < base.get("per_clip", {}).get(c, -1e9))
        if base and me.get("psnr", 1e9) < base["psnr"]:
            out.append(f"- Below `{BASELINE}` on the {split} split's mean ({me['psnr'] - base['psnr']:+.2f} dB).")
        if below:
            out.append(f"- Below `{BASELINE}` on {len(below)} {split} clip(s): {', '.join(below)}.")
    for where, wc in val_records(meta).items():
        groups = {g: v for g, v in (wc.get("per_group") or {}).items() if v < 0}
        if groups:
            out.append(f"- Below the baseline on {where} by group: "
                       + ", ".join(f"{g} {v:+.2f} dB" for g, v in groups.items()) + ".")
    rule = meta.get("val_rule") or {}
    if rule.get("reasons") or rule.get("forced"):
        out.append(f"- Val rule: {'; '.join(rule.get('reasons') or [])}{' (forced)' if rule.get('forced') else ''}.")
    out.append("- It needs the HR G-buffers listed under Inputs, rendered with the conventions of docs/clip-format.md "
               "(demodulation by the pre-integrated BRDF, exposure, jitter); frames from another renderer must "
               "follow them.")
    return out


def _before_line(meta: dict) -> list[str]:
    """The weights these replaced, on the same val clips (``val_rule.shipped_before``: release_weights.py records it)."""
    before = (meta.get("val_rule") or {}).get("shipped_before") or {}
    base = ((meta.get("scores_on_val_split") or {}).get(BASELINE) or {}).get("psnr")
    if not before or base is None:
        return []
    return [f"- The weights these replaced, on the same val clips: PSNR {before['psnr']:.2f} dB, margin "
            f"{before['psnr'] - base:+.2f} dB over `{BASELINE}`"
            + (f" (smallest per clip {before['margin_min']:+.2f} dB)" if before.get("margin_min") is not None else "")
            + "."]


def card_text(stem: str, meta: dict, spec_text: str | None, readme: str | None, buffers: dict,
              repo: Path = REPO) -> str:
    """The markdown card of the weights ``stem`` (``training/weights/<stem>.json`` read as ``meta``)."""
    model = meta["model"]
    name = next((n for n, f in PRETRAINED.items() if Path(f).stem == stem), model)
    info = MODELS.get(model)
    bufs = (buffers.get("models") or {}).get(model) or []
    lines = [f"# Model card: `{PREFIX}{name}`", "",
             f"Generated by `make generate` from [training/weights/{stem}.json]"
             f"(../../../training/weights/{stem}.json), the dataset spec it names and ../shared/scenes/README.md; "
             "do not edit (a test fails when it is stale).", "",
             "## What it is for", "",
             f"{info.description if info else model}. It upscales path-traced frames {meta['scale']}x in real-time "
             "rendering's setting: a low-resolution radiance frame with full-resolution G-buffers. Use it with "
             f"`blendsr upscale --model {PREFIX}{name}`, `blendsr evaluate`, `blendsr bench models`, the add-on's "
             f"preview, or as the start of a fine-tune (`run.init_from = \"{PREFIX}{name}\"`).", "",
             "## Inputs", "",
             f"Clip buffers (docs/clip-format.md): {', '.join(f'`{b}`' for b in bufs) or 'see its model page'}; "
             f"`blendsr render --for-models {model}` renders what it reads.", "",
             "## Weights", "",
             f"`training/weights/{meta.get('file')}`: {meta.get('bytes', 0):,} bytes, sha256 `{meta.get('sha256')}`, "
             f"{meta.get('params', 0):,} parameters, step {meta.get('step')}, {meta.get('date')}."]
    lines += ["", "## Training data", "", *_data_lines(meta, spec_text, readme)]
    test = meta.get("scores_on_test_split") or {}
    lines += ["", "## Margins (as recorded in the JSON)", "",
              f"- Test split: {_margin(test, model) if test else meta.get('test_split', 'not recorded')}.",
              f"- Val split: {_margin(meta.get('scores_on_val_split') or {}, model)}."]
    lines += _before_line(meta)
    for where, wc in val_records(meta).items():
        groups = ", ".join(f"{g} {v:+.2f} dB" for g, v in (wc.get("per_group") or {}).items())
        lines.append(f"- Worst case on val ({where}, {wc.get('frames')} frames): margin "
                     f"{wc.get('margin', 0):+.2f} dB, smallest per clip {wc.get('margin_min', 0):+.2f} dB"
                     + (f"; by group {groups}" if groups else "") + ".")
    metric = (test or meta.get("scores_on_val_split") or {}).get("metric", "?")
    lines += [f"- Metric: {metric}; margin = PSNR minus "
              f"`{BASELINE}`'s on the same frames."]
    lines += ["", "## Speed", "", *speed_lines(model, int(meta.get("params") or 0), repo)]
    lines += ["", "## Limits", "", *_limit_lines(meta, model), ""]
    return "\n".join(lines)


def cards(repo: Path = REPO, scenes_readme: Path = SCENES_README) -> dict[Path, str]:
    """{card path: text} of every shipped weights JSON."""
    try:
        readme = scenes_readme.read_text(encoding="utf-8")
    except OSError:
        readme = None
    buffers = json.loads(BUFFERS_JSON.read_text())
    out = {}
    for f in PRETRAINED.values():
        meta_path = WEIGHTS_DIR / (Path(f).stem + ".json")
        if not meta_path.is_file():
            continue
        meta = json.loads(meta_path.read_text())
        try:
            spec_text = (repo / meta["dataset"]["spec_file"]).read_text(encoding="utf-8")
        except (OSError, KeyError):
            spec_text = None
        out[CARDS_DIR / f"{meta_path.stem}.md"] = card_text(meta_path.stem, meta, spec_text, readme, buffers, repo)
    return out


def stale(repo: Path = REPO, scenes_readme: Path = SCENES_README) -> list[str]:
    """The cards whose file differs from what the generator writes now (missing ones included)."""
    return [str(p.relative_to(repo)) for p, text in cards(repo, scenes_readme).items()
            if not p.is_file() or p.read_text(encoding="utf-8") != text]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--check", action="store_true", help="only name the stale cards (exit 1 when any)")
    a = p.parse_args(argv)
    if a.check:
        bad = stale()
        for b in bad:
            print(f"{b}: stale (run make generate)")
        return 1 if bad else 0
    from training.run import write_text_atomic
    CARDS_DIR.mkdir(parents=True, exist_ok=True)
    for path, text in cards().items():
        write_text_atomic(path, text)
        print(f"wrote {path.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
