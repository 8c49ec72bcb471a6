"""The demo's fine-tune speed on an idle and on a loaded machine: steps per second of ``blendsr demo``'s fine-tune
(the shipped FuseSR-l, batch 4, LR crop 32: ``training.commands.demo.fine_tune``) for each thread count, alone and
beside LOAD busy processes at normal priority (another job on the machine, as a shared workstation or CI runner has).

    .venv/bin/python benchmarks/demo_speed.py DEMO_DIR -o OUT [--steps 30] [--threads 1,2] [--load 0,2]

DEMO_DIR is a ``blendsr demo --render-only -o DEMO_DIR`` output (its fine-tuning clip). Each (load, threads) pair
fine-tunes afresh in OUT/runs for ``--steps`` steps; the rate is (steps - 5) over the time from step 5 to the last
step in the run's log.csv (the first steps load the clip and warm up). Writes OUT/demo_speed.json and OUT/demo_speed.md.
Run it with nothing else working on the machine for the "idle" rows to mean idle.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
WARM_STEPS = 5
BUSY = "while True:\n    pass\n"


def step_times(run_dir: Path) -> dict[int, float]:
    """{step: seconds since the run started} from the run's log.csv (a row every ``run.log_every`` steps)."""
    import csv
    with open(run_dir / "log.csv", newline="") as f:
        return {int(r["step"]): float(r["elapsed_s"]) for r in csv.DictReader(f) if r.get("elapsed_s")}


def measure(clip: Path, out: Path, steps: int, threads: int, load: int) -> dict:
    """Fine-tune afresh with ``threads`` beside ``load`` busy processes; steps per second after the warm-up."""
    import shutil
    from training.commands.demo import fine_tune
    run_dir = out / "runs" / f"load{load}_threads{threads}"
    shutil.rmtree(run_dir, ignore_errors=True)
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(load)]
    try:
        t0 = time.monotonic()
        summary = fine_tune(run_dir, "fusesr-l", "pretrained:fusesr-l", [str(clip)], steps, threads)
        wall = time.monotonic() - t0
    finally:
        for p in busy:
            p.kill()
            p.wait()
    t = step_times(run_dir)
    first = min(s for s in t if s >= WARM_STEPS)
    rate = (max(t) - first) / (t[max(t)] - t[first])
    return {"load": load, "threads": threads, "steps": int(summary["step"]), "steps_per_s": rate,
            "s_per_step": 1.0 / rate, "wall_s": wall}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("demo_dir", type=Path, help="a `blendsr demo --render-only` output folder")
    p.add_argument("-o", "--out", type=Path, required=True)
    p.add_argument("--steps", type=int, default=30, help="fine-tuning steps per measurement (default 30)")
    p.add_argument("--threads", default="1,2", help="torch thread counts to measure (default 1,2)")
    p.add_argument("--load", default="0,2", help="busy processes beside the fine-tune (default 0,2)")
    a = p.parse_args(argv)
    clips = sorted((a.demo_dir / "clips").glob("finetune_seed*"))
    if not clips:
        raise SystemExit(f"{a.demo_dir}: no fine-tuning clip (run `blendsr demo --render-only -o {a.demo_dir}`)")
    a.out.mkdir(parents=True, exist_ok=True)
    rows = [measure(clips[0], a.out, a.steps, int(t), int(n))
            for n in a.load.split(",") for t in a.threads.split(",")]
    record = {"command": " ".join(["benchmarks/demo_speed.py", *(argv or sys.argv[1:])]),
              "date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count(), "clip": clips[0].name, "rows": rows}
    from gbuffer_export.clip import write_json_atomic
    write_json_atomic(a.out / "demo_speed.json", record)
    lines = ["| busy processes beside it | threads | steps/s | s/step |", "|---|---|---|---|"]
    lines += [f"| {r['load']} | {r['threads']} | {r['steps_per_s']:.2f} | {r['s_per_step']:.2f} |" for r in rows]
    (a.out / "demo_speed.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
