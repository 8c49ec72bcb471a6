"""How far a reader follows the render setup: the project's own calls from ``render_clip(cfg)`` until the clip's
``RenderContext`` is built (issue 59, item 5).

Two tiny renders, each in a process of its own (bpy state is per process): (a) the built-in scene and (b) a level
of ``../shared/scenes`` (a walk clip of garage.gltf, 32x18 HR, 1 spp, 1 frame, the default light auto: it goes
through the importer, the unit scale, the sky-mesh detection, level cameras and the light probe). Each runs under
``sys.setprofile``; only functions of ``gbuffer_export`` count (not bpy, the standard library or numpy; generator
expressions, comprehensions, class and module bodies left out). No frame is rendered: the trace stops when the
``RenderContext`` is built and the frame loop is replaced by a stop.

Counted per case, on the sequence of first calls of each function (the call tree printed below, depth-indented):
  functions  distinct project functions called;
  files      project files they live in;
  re-entries calls into a file after the trace had left that file for another project file (the zig-zag a reader
             follows); ``all calls`` and ``re-entries over all calls`` count every call, repeats included.
Each case gets two rows: the whole trace, and what a reader meets within ``READER_DEPTH`` calls of
``render_clip`` (render_clip, what it calls, and so on three levels down).

    python benchmarks/render_trace.py [--out docs/bench/render_trace/trace.txt] [--label main] [--level FILE]
"""
from __future__ import annotations

import argparse
import datetime
import inspect
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = str(REPO / "gbuffer_export") + os.sep
LEVEL = REPO.parent / "shared" / "scenes" / "levels" / "garage" / "garage.gltf"
CASES = ("builtin", "level")
#: The reader's rows count calls at most this deep below render_clip (render_clip itself: 0).
READER_DEPTH = 3


class _Stop(Exception):
    """Raised instead of rendering the frames: the trace ends at the RenderContext."""


def _config(case: str, out: Path, level: Path):
    from gbuffer_export.config import RenderConfig
    common = dict(output=out, hr_size=(32, 18), scales=(2,), hr_spp=1, lr_spp=1, gbuffer_spp=1, frames=(1, 1),
                  threads=1, progress=False)
    if case == "builtin":
        return RenderConfig(**common)
    return RenderConfig(scene=level, camera_path="walk", **common)


def trace_case(case: str, out: Path, level: Path = LEVEL) -> dict:
    """Run ``render_clip`` of ``case`` under the profiler until its RenderContext; the calls in order."""
    from gbuffer_export.blender import render
    calls: list[tuple[int, str, str]] = []  # (depth, file, function) of every project call
    depth = [0]
    ctx_init = render.RenderContext.__init__.__code__
    state = {"on": True}

    def profile(frame, event, arg):
        if not state["on"]:
            return
        code = frame.f_code
        if event == "call" and code is ctx_init:
            state["on"] = False
            return
        if (event not in ("call", "return") or not code.co_filename.startswith(PACKAGE) or code.co_name[0] == "<"
                or not code.co_flags & inspect.CO_OPTIMIZED):  # a class or module body run by a first import
            return
        if event == "call":
            rel = code.co_filename[len(str(REPO)) + 1:]
            calls.append((depth[0], rel, code.co_qualname))
            depth[0] += 1
        else:
            depth[0] -= 1

    def stop(ctx, todo):
        raise _Stop

    render._render_frames = stop
    cfg = _config(case, out, level)
    sys.setprofile(profile)
    try:
        render.render_clip(cfg)
    except _Stop:
        pass
    finally:
        sys.setprofile(None)
    if state["on"]:
        raise SystemExit(f"render_trace: {case}: no RenderContext was built")
    return {"case": case, "calls": calls}


def reentries(files: list[str]) -> int:
    """Calls into a file after the sequence had left that file for another one."""
    seen, n, prev = set(), 0, None
    for f in files:
        if f != prev and f in seen:
            n += 1
        seen.add(f)
        prev = f
    return n


def summarise(calls: list) -> dict:
    first, tree = {}, []
    for d, f, fn in calls:
        if (f, fn) not in first:
            first[(f, fn)] = d
            tree.append((d, f, fn))
    return {"functions": len(first), "files": len({f for _, f, _ in tree}),
            "reentries": reentries([f for _, f, _ in tree]), "all_calls": len(calls),
            "reentries_all_calls": reentries([f for _, f, _ in calls]), "tree": tree}


def _child(case: str, level: Path) -> dict:
    import tempfile
    with tempfile.TemporaryDirectory(prefix="render-trace-") as tmp:
        proc = subprocess.run([sys.executable, __file__, "--case", case, "--clip", str(Path(tmp) / "clip"),
                               "--level", str(level)],
                              capture_output=True, text=True, cwd=REPO, timeout=900)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("TRACE ")]
    if proc.returncode or not lines:
        raise SystemExit(f"render_trace: {case}: the traced render failed (exit {proc.returncode}): "
                         f"{(proc.stderr.strip().splitlines() or ['no output'])[-1]}")
    return json.loads(lines[-1][len("TRACE "):])


def report(results: dict, label: str, command: str) -> str:
    head = [f"# render setup trace ({label})", f"command: {command}",
            f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}", "",
            "case                functions  files  re-entries  all calls  re-entries over all calls"]
    body = []
    for name, s in results.items():
        head.append(f"{name:19} {s['functions']:9d}  {s['files']:5d}  {s['reentries']:10d}  {s['all_calls']:9d}  "
                    f"{s['reentries_all_calls']:9d}")
        if "tree" in s:
            body += ["", f"## {name}: call tree (first call of each function; depth 0: render_clip)"]
            body += [f"{'  ' * max(d, 0)}{fn}  [{f}]" for d, f, fn in s["tree"]]
    return "\n".join(head + body) + "\n"


def measure(level: Path) -> dict:
    """Every case's counts, whole and within ``READER_DEPTH`` (without the tree)."""
    out = {}
    for case in CASES:
        calls = _child(case, level)["calls"]
        out[case] = summarise(calls)
        reader = summarise([c for c in calls if c[0] <= READER_DEPTH])
        out[f"{case} (depth<={READER_DEPTH})"] = {k: v for k, v in reader.items() if k != "tree"}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write the report here (and a .json of the counts beside it)")
    ap.add_argument("--label", default="this checkout", help="what was measured (e.g. main, stages)")
    ap.add_argument("--level", type=Path, default=LEVEL, help="the level of case (b) (default: %(default)s)")
    ap.add_argument("--case", choices=CASES, help=argparse.SUPPRESS)
    ap.add_argument("--clip", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.case:  # the child: one traced render
        sys.path.insert(0, str(REPO))
        print("TRACE " + json.dumps(trace_case(a.case, a.clip, a.level)))
        return 0
    if not a.level.is_file():
        raise SystemExit(f"render_trace: {a.level}: the level is missing (../shared/scenes)")
    results = measure(a.level.resolve())
    command = shlex.join(["python", "benchmarks/render_trace.py", *(argv if argv is not None else sys.argv[1:])])
    text = report(results, a.label, command)
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)
        counts = {c: {k: v for k, v in s.items() if k != "tree"} for c, s in results.items()}
        a.out.with_suffix(".json").write_text(json.dumps({"label": a.label, "command": command,
                                                          "counts": counts}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
