"""What a dataset render has done and what it costs, measured from its own records (``blendsr dataset --status``).

The cost of a frame is its ``seconds_total`` in ``CLIP/frames/NNNNNN.json``: the wall time of the frame's every
level and pass (G-buffers, LR and HR radiance, conversion, writing), from the start of the frame to its commit. A
clip's setup (import, camera planning, BVH build) is not in it, so the sum is the rendering proper; the remaining
time is estimated per source (``levels``, ``builtin``, ``assets``...) as its unrendered frames times the median of its
finished ones (the median over all sources where a source has none finished yet), for one worker on the machine and
load the finished frames were rendered on. No bpy: the numpy core's layer.
"""
from __future__ import annotations

import json
import statistics
from pathlib import Path

from ..errors import BlendSRError


def frame_seconds(clip_dir: Path) -> list[float]:
    """``seconds_total`` of every committed frame record of ``clip_dir`` (frames rendered before the field existed, or
    unreadable records, are skipped)."""
    out = []
    for rec in sorted((clip_dir / "frames").glob("*.json")):
        try:
            s = json.loads(rec.read_text()).get("seconds_total")
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(s, (int, float)) and s >= 0:
            out.append(float(s))
    return out


def _group(clips: list[dict], root: Path) -> dict:
    seconds = [s for c in clips for s in frame_seconds(root / c["path"])]
    planned = sum(int(c["frames_planned"]) for c in clips)
    done = sum(int(c["frames_done"]) for c in clips)
    return {"clips": len(clips), "clips_done": sum(c["state"] == "done" for c in clips),
            "frames_planned": planned, "frames_done": done, "frames_timed": len(seconds),
            "render_s": sum(seconds), "median_s_per_frame": statistics.median(seconds) if seconds else None,
            "p90_s_per_frame": _quantile(seconds, 0.9),
            "hr_pixels_done": sum(int(c["frames_done"]) * _hr_pixels(c) for c in clips)}


def _hr_pixels(clip: dict) -> int:
    w, h = clip["render"]["hr_size"]
    return int(w) * int(h)


def _quantile(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def dataset_status(root: Path) -> dict:
    """Per source, per split and in all: clips and frames planned and done, render seconds, median and p90 seconds
    per frame, and the estimated seconds left (one worker, see the module's docstring)."""
    index_file = Path(root) / "dataset.json"
    try:
        index = json.loads(index_file.read_text())
        clips = index["clips"]
    except FileNotFoundError:
        raise BlendSRError(f"{index_file}: no dataset index (render the dataset first: blendsr dataset SPEC -o "
                           f"{root})") from None
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise BlendSRError(f"{index_file}: not a dataset index ({exc})") from None
    report = {"dataset": index.get("name"), "all": _group(clips, root), "by_source": {}, "by_split": {}}
    for key, field in (("by_source", "source"), ("by_split", "split")):
        for value in sorted({c[field] for c in clips}):
            report[key][value] = _group([c for c in clips if c[field] == value], root)
    fallback = report["all"]["median_s_per_frame"]
    left = 0.0
    for g in report["by_source"].values():
        rate = g["median_s_per_frame"] if g["median_s_per_frame"] is not None else fallback
        g["estimate_left_s"] = None if rate is None else (g["frames_planned"] - g["frames_done"]) * rate
        g["estimate_from"] = "own" if g["median_s_per_frame"] is not None else "all"
        left += g["estimate_left_s"] or 0.0
    report["all"]["estimate_left_s"] = left if fallback is not None else None
    return report


def status_lines(report: dict) -> list[str]:
    """The report as lines: one per source, then the total."""
    def line(name: str, g: dict) -> str:
        med = "-" if g["median_s_per_frame"] is None else f"{g['median_s_per_frame']:.1f}"
        left = "-" if g.get("estimate_left_s") is None else f"{g['estimate_left_s'] / 3600:.1f}"
        left += "*" if g.get("estimate_from") == "all" else ""
        return (f"{name:18s} {g['clips_done']:5d}/{g['clips']:<5d} {g['frames_done']:6d}/{g['frames_planned']:<6d} "
                f"{g['hr_pixels_done'] / 1e6:8.1f} {g['render_s'] / 3600:9.2f} {med:>9s} {left:>9s}")
    head = (f"{'source':18s} {'clips':>11s} {'frames':>13s} {'M HR px':>8s} {'render h':>9s} {'s/frame':>9s} "
            f"{'h left':>9s}")
    rows = [line(k, g) for k, g in report["by_source"].items()] + [line("all", report["all"])]
    splits = ", ".join(f"{k} {g['clips_done']}/{g['clips']} clips ({g['hr_pixels_done'] / 1e6:.1f} M HR px)"
                       for k, g in report["by_split"].items())
    return [head, *rows, f"splits: {splits}",
            "s/frame: median wall time of a finished frame (all levels and passes, no clip setup); h left: the "
            "unrendered frames at that median, one worker (*: a source with no finished frame, at the median of all)"]
