"""What the training loop does around each step, as hooks over a ``training.trainer.Trainer``: ``RunLog`` (log.csv,
TensorBoard, the progress bar), ``Checkpoints`` (last.pt and step_NNNNNNNN.pt) and ``Evaluations`` (held-out
frames and clips every ``run.eval_every`` steps and at the end). A hook has ``on_step(trainer, info)`` and
``close(trainer, exc)``; only rank 0 writes files.
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import torch

from gbuffer_export.clip import write_json_atomic
from gbuffer_export.errors import with_path
from training.checkpoint import save_checkpoint

LOG_COLUMNS = ("step", "loss", "pixel", "ssim", "fft", "temporal", "perceptual", "baseline", "lr", "step_ms",
               "data_ms", "samples_per_s", "elapsed_s", "mem_mb")


@dataclass
class StepInfo:
    """One finished step: ``loss`` (tensor), ``terms`` ({name: tensor}), seconds waiting for data and for the
    whole step, ``elapsed`` (seconds of the run, earlier invocations included), ``budget_s`` (this invocation's)."""

    step: int
    loss: torch.Tensor
    terms: dict
    data_s: float
    step_s: float
    elapsed: float
    budget_s: float


def progress_kwargs(cfg, step: int) -> dict:
    """tqdm's total/initial/unit: a ``run.minutes`` budget counts seconds of that budget (its steps are unknown:
    counting to ``run.max_steps`` would show an ETA of days), otherwise steps up to ``run.max_steps``."""
    if cfg.run.minutes:
        return {"total": max(int(round(60 * cfg.run.minutes)), 1), "initial": 0, "unit": "s"}
    return {"total": cfg.run.max_steps, "initial": step, "unit": "step"}


def peak_memory_mb(device: torch.device) -> float:
    """Peak memory since the last call: CUDA memory allocated by torch on a GPU (the peak is reset), else the
    process's peak resident set size (never reset: the maximum so far)."""
    if device.type == "cuda":
        mb = torch.cuda.max_memory_allocated(device) / 2**20
        torch.cuda.reset_peak_memory_stats(device)
        return mb
    from gbuffer_export.resources import peak_rss_bytes  # getrusage or, on Windows, psutil
    peak = peak_rss_bytes()
    return peak / 2**20 if peak is not None else 0.0


def drop_rows_after(path: Path, step: int) -> list[str]:
    """A resumed run's log.csv without the rows logged after ``step`` (the checkpoint it resumes from: those steps
    run again and are logged again) and without a last row cut short by a kill (no newline at its end), rewritten
    atomically when any is dropped; returns its header row."""
    with open(path, newline="") as f:
        text = f.read()
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        return []
    header, body = rows[0], rows[1:]
    torn = len(rows) > 1 and not text.endswith("\n")
    col = header.index("step") if "step" in header else None
    keep = [r for r in body[:len(body) - torn]
            if col is None or len(r) <= col or not r[col].isdigit() or int(r[col]) <= step]
    if len(keep) < len(body):
        from training.run import write_text_atomic
        text = io.StringIO()
        csv.writer(text).writerows([header, *keep])
        write_text_atomic(path, text.getvalue(), newline="")
    return header


class RunLog:
    """log.csv every ``run.log_every`` steps (and the last), TensorBoard scalars when it is installed, the tqdm
    bar with ``run.progress``; ``mem_peak`` is the largest logged memory (MiB)."""

    def __init__(self, trainer, run_dir: Path):
        cfg, main = trainer.cfg, trainer.dist.main
        self.mem_peak = 0.0
        self.logf = self.writer = self.tb = self.bar = None
        self.columns = LOG_COLUMNS
        if main:
            path = self.path = run_dir / "log.csv"
            header = []
            if path.exists():  # a resumed run keeps the columns its log started with (an older version's, too)
                header = drop_rows_after(path, trainer.step_no)
            if header:
                self.columns = tuple(header)
            self.logf = open(path, "a", newline="")
            self.writer = csv.writer(self.logf)
            if not header:
                self.writer.writerow(self.columns)
            try:
                from torch.utils.tensorboard import SummaryWriter
                # a resumed run hides the events logged after its checkpoint, as log.csv drops their rows
                purge = trainer.step_no + 1 if header else None
                self.tb = SummaryWriter(str(run_dir / "tensorboard"), purge_step=purge)
            except ImportError:
                self.tb = None
        if cfg.run.progress and main:
            from tqdm import tqdm
            self.bar = tqdm(**progress_kwargs(cfg, trainer.step_no), desc=f"train {cfg.model.name}",
                            dynamic_ncols=True)

    def on_step(self, trainer, info: StepInfo) -> None:
        cfg = trainer.cfg
        samples_s = cfg.data.batch_size * trainer.dist.world / info.step_s
        if self.bar is not None:
            self._bar(cfg, info, samples_s)
        if info.step % cfg.run.log_every == 0 or info.step == cfg.run.max_steps:
            row = {"step": info.step, "loss": info.loss.item(), **{k: v.item() for k, v in info.terms.items()},
                   "lr": trainer.scheduler.get_last_lr()[0], "step_ms": 1000 * info.step_s,
                   "data_ms": 1000 * info.data_s, "samples_per_s": samples_s, "elapsed_s": info.elapsed,
                   "mem_mb": peak_memory_mb(trainer.device)}
            self.mem_peak = max(self.mem_peak, row["mem_mb"])
            if self.writer is not None:
                try:
                    self.writer.writerow(["" if row.get(c) is None else row.get(c, "") for c in self.columns])
                    self.logf.flush()
                except OSError as exc:  # a full disk: the one-line error names log.csv
                    raise with_path(exc, self.path) from exc
            if self.tb is not None:
                for k, v in row.items():
                    if k != "step":
                        self.tb.add_scalar(k, v, info.step)

    def _bar(self, cfg, info: StepInfo, samples_s: float) -> None:
        bar = self.bar
        if cfg.run.minutes:  # a time budget: the bar counts its seconds, the postfix the steps
            bar.update(max(min(int(info.budget_s), bar.total) - bar.n, 0))
        else:
            bar.update(1)
        post = {"step": info.step} if cfg.run.minutes else {}
        post |= {"loss": f"{info.loss.item():.4f}", "samples_s": f"{samples_s:.1f}"}
        if cfg.run.minutes:  # the time budget often ends the run long before max_steps (bar's ETA)
            post["min_left"] = f"{max(cfg.run.minutes - info.budget_s / 60, 0):.1f}"
        bar.set_postfix(post)

    def close(self, trainer, exc) -> None:
        if self.bar is not None:
            self.bar.close()
        if self.logf is not None:
            try:
                self.logf.close()
            except OSError as err:  # the rows a full disk refused: after another error, that error is the news
                if exc is None:
                    raise with_path(err, self.path) from err
        if self.tb is not None:
            self.tb.close()


class Checkpoints:
    """RUN/checkpoints/last.pt every ``run.checkpoint_every`` steps (with a numbered copy, the newest
    ``run.keep_checkpoints`` kept) and when the run stops or is interrupted; never after a failed step.
    ``record`` is what every checkpoint holds beside the trainer's state (configurations, clips' hashes, scales)."""

    def __init__(self, trainer, run_dir: Path, record: dict):
        self.dir = run_dir / "checkpoints"
        self.last = self.dir / "last.pt"
        self.record = record
        trainer.checkpoint_path = self.last

    def save(self, trainer, elapsed: float, numbered: bool) -> None:
        if not trainer.dist.main:
            return
        st = {**self.record, **trainer.state_dict(), "elapsed_s": elapsed}
        save_checkpoint(self.last, st)
        if numbered:
            save_checkpoint(self.dir / f"step_{trainer.step_no:08d}.pt", st)
            olds = sorted(self.dir.glob("step_*.pt"))
            for p in olds[:max(len(olds) - trainer.cfg.run.keep_checkpoints, 0)]:
                p.unlink()

    def on_step(self, trainer, info: StepInfo) -> None:
        if info.step % trainer.cfg.run.checkpoint_every == 0 and info.step < trainer.cfg.run.max_steps:
            self.save(trainer, info.elapsed, numbered=True)

    def close(self, trainer, exc, elapsed: float = 0.0, interrupted: bool = False) -> None:
        """On a clean stop or an interrupt; after any other exception the last checkpoint stays the last good one."""
        if exc is None or interrupted:
            self.save(trainer, elapsed, numbered=exc is None and trainer.step_no == trainer.cfg.run.max_steps)


class Evaluations:
    """Held-out frames (``data.val_frames``) and clips (``data.val_clips``) scored with the evaluated weights
    every ``run.eval_every`` steps (val_step_N.json, val_clips_step_N.json) and at the end (val.json,
    val_clips.json); rank 0 only."""

    def __init__(self, trainer, run_dir: Path, caches):
        self.run_dir, self.caches = run_dir, caches

    def on_step(self, trainer, info: StepInfo) -> None:
        cfg = trainer.cfg
        if cfg.run.eval_every and info.step % cfg.run.eval_every == 0 and trainer.dist.main:
            self.evaluate(trainer, f"_step_{info.step:08d}")
            trainer.net.train()

    def evaluate(self, trainer, suffix: str = "") -> dict:
        """{'val': mean, 'val_clips': mean} of what the configuration asks for; writes the JSON files."""
        cfg, out = trainer.cfg, {}
        if cfg.data.val_frames:
            out["val"] = validate_frames(trainer.evaluated(), self.caches, cfg,
                                         self.run_dir / f"val{suffix}.json", trainer.device, trainer.dtype)["mean"]
        if cfg.data.val_clips:
            out["val_clips"] = validate_clips(trainer.evaluated(), cfg, self.run_dir / f"val_clips{suffix}.json",
                                              trainer.device, trainer.dtype)["mean"]
        return out

    def close(self, trainer, exc) -> None:
        pass


def _evaluated(model, cfg, device):
    """The trained module as an ``InferenceModel`` on ``device`` with the run's demodulation eps."""
    from training.inference.model import InferenceModel
    return InferenceModel(model, demod_eps=cfg.data.demod_eps).to(device)


def validate_clips(model, cfg, out: Path, device, dtype) -> dict:
    """Evaluate the whole ``data.val_clips`` (clips never trained on); writes ``out``."""
    from training.evaluate import EvalOptions, evaluate_model
    result = evaluate_model(_evaluated(model, cfg, device), list(cfg.data.val_clips),
                            EvalOptions(amp=dtype, flip=False, baseline=None))
    write_json_atomic(out, result)
    model.train()
    return result


def validate_frames(model, caches, cfg, out: Path, device, dtype) -> dict:
    """Evaluate the held-out last ``data.val_frames`` frames of every training clip; writes ``out``."""
    from training.evaluate import EvalOptions, evaluate_model
    frames = {str(c.clip_path): c.frames[-cfg.data.val_frames:] for c in caches}
    scales: dict[str, list[float]] = {}
    for c in caches:  # one cache per clip and scale
        scales.setdefault(str(c.clip_path), []).append(float(c.scale))
    result = evaluate_model(_evaluated(model, cfg, device), list(dict.fromkeys(c.clip_path for c in caches)),
                            EvalOptions(frames=frames, amp=dtype, flip=False, scales=scales, baseline=None))
    write_json_atomic(out, result)
    model.train()
    return result
