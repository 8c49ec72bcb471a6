"""``blendsr demo`` end to end at a tiny size: it renders the buffers every shipped network reads and scores all of
them (a shipped network whose buffer the demo did not render failed the demo after the fact)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("bpy")
pytest.importorskip("torch")
pytestmark = [pytest.mark.bpy, pytest.mark.torch]
ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.heavy
def test_demo_scores_every_shipped_network_on_its_own_clips(tmp_path):
    from training.pretrained import available
    r = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "demo", "-o", str(tmp_path / "d"),
                        "--hr-size", "64x36", "--frames", "1:2", "--hr-spp", "2", "--lr-spp", "2",
                        "--no-hr-denoise", "--train-steps", "0"],
                       capture_output=True, text=True, cwd=ROOT, timeout=900,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-3000:]
    scored = [line.split()[0] for line in r.stdout.splitlines() if " PSNR " in line]
    assert {"bicubic", "demod-jbu", *available()} <= set(scored), scored
    assert (tmp_path / "d" / "side_by_side.png").is_file() and (tmp_path / "d" / "contact_sheet.png").is_file()


def _demo(out, *extra):
    import subprocess as sp
    return sp.Popen([sys.executable, "-m", "gbuffer_export.cli", "demo", "-o", str(out), "--hr-size", "64x36",
                     "--frames", "1:2", "--hr-spp", "1", "--lr-spp", "1", "--no-hr-denoise", "--threads", "1",
                     *extra], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=sp.PIPE,
                    stderr=sp.STDOUT, text=True)


def _signal_when(proc, ready, sig, timeout=600):
    """Send ``sig`` once ``ready()`` holds; returns (seconds the demo took to exit after it, its output)."""
    import signal as _signal  # noqa: F401
    import time
    deadline = time.monotonic() + timeout
    try:
        while not ready():
            assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read() if proc.poll() else ""
            time.sleep(0.2)
        t0 = time.monotonic()
        proc.send_signal(sig)
        proc.wait(timeout=60)
        return time.monotonic() - t0, proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.heavy
def test_sigterm_and_sigint_stop_the_demo_within_seconds_and_it_continues(tmp_path):
    """Issue 57 item 3: SIGTERM during the fine-tune and SIGINT during a render each stop ``blendsr demo`` within
    seconds, with nothing recorded as done; the same command then continues (the fine-tune from its checkpoint)."""
    import signal
    out = tmp_path / "d"
    run = out / "run_fusesr_l_finetuned"
    log = run / "log.csv"
    took, text = _signal_when(_demo(out, "--train-steps", "100000"),
                              lambda: log.is_file() and len(log.read_text().splitlines()) >= 2, signal.SIGTERM)
    assert took < 15 and "interrupted; rerun the same command to resume" in text, (took, text[-3000:])
    summary = json.loads((run / "summary.json").read_text())
    assert summary["stopped_by"] == "signal" and summary["step"] < 100000
    assert not (out / "demo_summary.json").exists() and not (out / "pareto.png").exists()
    ran = summary["step"]
    # SIGINT (Ctrl-C sent to the demo alone) while another demo renders: the render stops too
    again = _demo(tmp_path / "e", "--train-steps", "0")
    took, text = _signal_when(again, lambda: (tmp_path / "e" / "clips").is_dir(), signal.SIGINT)
    assert took < 15 and again.returncode == 130, (took, text[-3000:])
    # the same command with a budget just above the steps run: continues, and every record names the steps run
    done = _demo(out, "--train-steps", str(ran + 2))
    text = done.communicate(timeout=900)[0]
    assert done.returncode == 0, text[-3000:]
    result = json.loads((out / "demo_summary.json").read_text())
    assert result["train"]["step"] == ran + 2 and result["train"]["stopped_by"] == "max_steps"
    label = f"fusesr-l (fine-tuned {ran + 2} steps)"
    assert result["bench"][-1]["model"] == label and label in (out / "bench" / "bench_models.md").read_text()
    steps = [int(r.split(",")[0]) for r in log.read_text().splitlines()[1:] if r]
    assert steps == sorted(set(steps))  # continued, not trained again from step 0
