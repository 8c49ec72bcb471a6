"""Issue 54: benchmarks/scale_round.sh (re)starts the scale round's background jobs, each at most once, and its
release order holds: the FuseSR fine-tune faces the val rule before the 10x run, and a run is released once."""
from __future__ import annotations

import fcntl
import os
import subprocess
import sys

from tests.conftest import REPO

SCRIPT = str(REPO / "benchmarks/scale_round.sh")


def _round(tmp_path, *jobs, dry=True):
    env = {**os.environ, "DRY": "1" if dry else "0", "PY": sys.executable, "RUNS": str(tmp_path / "runs"),
           "DATA": str(tmp_path / "ds")}
    return subprocess.run(["bash", SCRIPT, *jobs], env=env, capture_output=True, text=True, timeout=60)


def _steps(out):
    """{job: [its commands]} of a DRY run."""
    jobs, job = {}, None
    for line in out.stdout.splitlines():
        if line.startswith("== "):
            job = jobs.setdefault(line[3:], [])
        elif line.startswith("+ "):
            job.append(line[2:])
    return jobs


def test_every_job_in_order_and_the_fine_tune_released_before_the_10x_run(tmp_path):
    out = _round(tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    jobs = _steps(out)
    assert list(jobs) == ["render", "fusesr", "fusesr-10x", "fusesr-l", "fusesr-l-10x", "finetune", "inputs", "end"]
    ft = f"{tmp_path}/runs/finetune/fusesr"
    tenx = jobs["fusesr-10x"]
    assert "--train-only" in tenx[0] and f"exists('{ft}/released')" in tenx[1]
    assert f"--run fusesr={tmp_path}/runs/scaling/fusesr_470clips" in tenx[2] and "--defer-test" in tenx[2]
    tune = jobs["finetune"]
    assert "--list-clips" in tune[0] and "split_clips" in tune[1]
    assert "run.init_from=\"pretrained:fusesr\"" in tune[2] and "--max-steps 3000" in tune[2]
    assert f"--run fusesr={ft}" in tune[3]
    assert not (tmp_path / "runs" / "round-logs").exists()  # DRY starts nothing


def test_the_round_end_reads_test_only_after_every_release_and_records_val_before_generating(tmp_path):
    end = _steps(_round(tmp_path, "end"))["end"]
    waited = end[0]
    for marker in ("scaling/fusesr.scored", "scaling/fusesr-l.scored", "finetune/fusesr/released",
                   "scaling/fusesr_470clips/released", "scaling/fusesr-l_470clips/released"):
        assert f"{tmp_path}/runs/{marker}" in waited
    assert "--record-test" in end[1]
    at = {k: next(i for i, c in enumerate(end) if k in c) for k in
          ("--split test --models pretrained:nsrr-fec", "--record --scores", "training.commands.generate", "--combine",
           "family_gap")}
    assert list(at.values()) == sorted(at.values()) and at["--record --scores"] > 1
    assert sum("--split test --models" in c for c in end) == 10  # every baseline and shipped network


def test_the_inputs_study_is_the_1x_run_with_material_inputs_beside_a_second_seed_scored_on_val_only(tmp_path):
    steps = _steps(_round(tmp_path, "inputs"))["inputs"]
    base = f"{tmp_path}/runs/scaling/fusesr-l_047clips"
    study, seed = (f"{tmp_path}/runs/inputs/fusesr-l_047clips_{k}" for k in ("material", "seed1"))
    assert f"{base}/config.toml" in steps[0]
    assert steps[1].endswith(f"-o {study} --config {base}/config.toml --set model.fusesr-l.hr_material=true")
    assert steps[2].endswith(f"-o {seed} --config {base}/config.toml --set run.seed=1")
    assert all(r in steps[3] for r in (base, study, seed)) and "== 6000" in steps[3]
    assert len(steps) == 6 and "--split val" in steps[4] and "--split test" not in " ".join(steps)
    assert all(f"fusesr-l:{r}/checkpoints/last.pt" in steps[4] for r in (base, study, seed))
    assert "family_gap" in steps[5] and "--json" in steps[5]


def test_a_released_run_is_not_released_again(tmp_path):
    ft = tmp_path / "runs" / "finetune" / "fusesr"
    ft.mkdir(parents=True)
    (ft / "released").touch()
    out = _round(tmp_path, "finetune")
    assert out.returncode == 0 and "released already" in out.stdout and "release_weights" not in out.stdout


def test_a_running_job_is_not_started_twice_and_an_unknown_one_is_refused(tmp_path):
    logs = tmp_path / "runs" / "round-logs"
    logs.mkdir(parents=True)
    with open(logs / "fusesr.lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        out = _round(tmp_path, "fusesr", dry=False)
    assert out.returncode == 0 and "fusesr: running already" in out.stdout
    assert not (logs / "fusesr.log").exists()
    bad = _round(tmp_path, "fusesr-xl")
    assert bad.returncode == 2 and "unknown job 'fusesr-xl'" in bad.stderr
