"""One optimizer step of Arm's NSS-v1 model, by the model gym's own Trainer, on a BlendSR export.

Runs in the model gym's environment (it imports ng_model_gym, not BlendSR): benchmarks/check_nss_consumer.sh with
STEP=1 (CPU, up to the forward) or benchmarks/gpu/nss_gym_step.sh (CUDA, the whole step).

    python benchmarks/nss_gym_step.py SAFETENSORS_DIR WORK_DIR [--recurrent-samples 4] [--json OUT.json]

The config is the gym's own NSS template (ng_model_gym/usecases/nss/configs/nss_v1_template.json, validated by its
load_config_file) with only these keys changed: dataset.path (the export's safetensors), train.batch_size 1,
dataset.num_workers 0, train.perform_validate false, model.recurrent_samples, the output folders (under WORK_DIR,
tensorboard off) and the cosine schedule's warmup_percentage 0 (so the one step runs at the template's learning
rate rather than its min_lr). The Trainer builds the dataloader, LossV1, the NSSV1Model, AdamW and the schedule;
the step is Trainer._train_step, the body of Trainer.train's loop.

LossV1 builds lpips.LPIPS(net="alex"), whose ImageNet AlexNet torchvision downloads at run time. Without that
file in torch's hub cache (torch.hub.get_dir()/checkpoints/alexnet-owt-7be5be79.pth) the script says so, builds
LPIPS with its own pnet_rand=True (random backbone) and sets loss_args.lpips_weight = 0, so the loss is still the
gym's LossV1, less its LPIPS term.

Exit status: 0 the step ran (finite losses, finite gradients, parameters changed); 3 the forward refused a
non-CUDA device (the expected end on a machine without CUDA); 1 anything else. --json writes the record.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from importlib.resources import files
from pathlib import Path

import torch

log = logging.getLogger("nss_gym_step")
ALEXNET = "alexnet-owt-7be5be79.pth"  # the file torchvision's AlexNet_Weights.IMAGENET1K_V1 caches
CUDA_REFUSAL = "requires CUDA"


def write_json_atomic(path: Path, record: dict) -> None:
    """Write the record through a temporary file in the same folder, then rename it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(record, f, indent=2, default=str)
    os.replace(tmp, path)


def lpips_backbone_available() -> bool:
    return (Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET).is_file()


def use_random_lpips_backbone() -> None:
    """Make lpips.LPIPS build its backbone with random weights (its pnet_rand option): no download."""
    import lpips

    init = lpips.LPIPS.__init__

    def init_random(self, *args, **kwargs):
        kwargs["pnet_rand"] = True
        # lpips finds its linear layers' file beside the __init__ it inspects: name it, this one is elsewhere
        linear = Path(lpips.__file__).parent / "weights" / f"v{kwargs.get('version', '0.1')}"
        kwargs.setdefault("model_path", str(linear / f"{kwargs.get('net', 'alex')}.pth"))
        init(self, *args, **kwargs)

    lpips.LPIPS.__init__ = init_random


def write_config(st_dir: Path, work: Path, recurrent: int, lpips_ok: bool) -> Path:
    """The gym's NSS template with the keys named in the module docstring changed; returns its path."""
    template = files("ng_model_gym.usecases.nss.configs") / "nss_v1_template.json"
    cfg = json.loads(template.read_text())
    cfg["dataset"]["path"] = {"train": str(st_dir), "validation": None, "test": None}
    cfg["dataset"]["num_workers"] = 0
    cfg["model"]["recurrent_samples"] = recurrent
    cfg["train"]["batch_size"] = 1
    cfg["train"]["perform_validate"] = False
    cfg["train"]["fp32"]["lr_scheduler"]["warmup_percentage"] = 0.0
    cfg["train"]["fp32"]["checkpoints"]["dir"] = str(work / "checkpoints")
    cfg["output"]["dir"] = str(work / "output")
    cfg["output"]["tensorboard_output_dir"] = None
    if not lpips_ok:
        cfg["train"]["loss_args"]["lpips_weight"] = 0.0
    path = work / "nss_v1_blendsr.json"
    path.write_text(json.dumps(cfg, indent=2))
    return path


def build_trainer(config_path: Path):
    """The gym's Trainer on the config, as its do_training builds it (FP32, no resume, no fine-tune)."""
    import ng_model_gym.api  # noqa: F401  (registers the NSS model and dataset)
    from ng_model_gym.core.config.config_utils import load_config_file
    from ng_model_gym.core.trainer.trainer import Trainer
    from ng_model_gym.core.utils.enum_definitions import TrainEvalMode

    params = load_config_file(config_path)
    params.model_train_eval_mode = TrainEvalMode.FP32
    params.train.resume = None
    params.train.finetune = None
    return Trainer(params)


def batch_loss(trainer, batch, seed: int) -> float:
    """The loss on the batch as Trainer._train_step computes it, without gradients, from reset history."""
    from ng_model_gym.core.data.data_utils import move_to_device

    model = trainer.model
    model.on_train_epoch_start()  # resets the recurrent history buffers
    torch.manual_seed(seed)  # the same GT-history augmentation draw as the step's
    x, y = model.on_before_batch_transfer(batch)
    x, y = move_to_device(x, trainer.device), move_to_device(y, trainer.device)
    x, y = model.on_after_batch_transfer((x, y))
    model.y_true = y
    with torch.no_grad():
        return float(trainer._training_loss(y, trainer._training_model(x)))


def one_step(trainer, batch, seed: int) -> dict:
    """Trainer._train_step on the batch, between the hooks Trainer.train calls around it."""
    model = trainer.model
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    lr = trainer.optimizer.param_groups[0]["lr"]
    model.on_train_epoch_start()
    torch.manual_seed(seed)
    model.on_train_batch_start()
    _, loss, _ = trainer._train_step(*batch)
    model.on_train_batch_end()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    deltas = {n: float((p.detach() - before[n]).abs().max()) for n, p in model.named_parameters()}
    return {
        "lr": lr,
        "loss_in_step": float(loss),
        "grad_norm": float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads]))) if grads else 0.0,
        "grads_finite": all(bool(torch.isfinite(g).all()) for g in grads),
        "parameter_tensors": len(deltas),
        "parameter_tensors_changed": sum(d > 0 for d in deltas.values()),
        "max_abs_parameter_change": max(deltas.values(), default=0.0),
    }


def compile_slang(trainer, record: dict) -> None:
    """JIT-build the model's Slang module (slangc, then nvcc and ninja through torch's cpp_extension)."""
    t0 = time.perf_counter()
    try:
        trainer.model._get_slang()
        record["slang_build"] = f"ok in {time.perf_counter() - t0:.0f} s"
    except Exception as e:  # a diagnosis, reported in the record
        record["slang_build"] = f"failed after {time.perf_counter() - t0:.0f} s: {type(e).__name__}: {e}"[:2000]
    log.info("Slang build: %s", record["slang_build"])


def stage(record: dict, name: str, t0: float) -> None:
    record["stages"].append({"stage": name, "s": round(time.perf_counter() - t0, 2)})
    log.info("reached: %s (%.1f s)", name, time.perf_counter() - t0)


def shapes(value):
    if isinstance(value, dict):
        return {k: shapes(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [shapes(v) for v in value]
    return "x".join(map(str, value.shape)) if isinstance(value, torch.Tensor) else repr(value)


def prepare(args, record: dict, t0: float):
    """The config, the Trainer and one batch of the export; returns (trainer, batch)."""
    lpips_ok = lpips_backbone_available()
    record["lpips_backbone"] = ("ImageNet AlexNet from torch's hub cache" if lpips_ok else
                                "random (lpips pnet_rand), loss_args.lpips_weight = 0: no AlexNet weights here")
    if not lpips_ok:
        log.warning("no %s in %s: LPIPS term off (%s)", ALEXNET, torch.hub.get_dir(), record["lpips_backbone"])
        use_random_lpips_backbone()
    config = write_config(args.safetensors, args.work, args.recurrent_samples, lpips_ok)
    record["config"] = str(config)
    trainer = build_trainer(config)
    record["device"] = str(trainer.device)
    record["windows"] = len(trainer.train_dataloader.dataset)
    record["parameters"] = sum(p.numel() for p in trainer.model.parameters())
    record["loss"] = type(trainer.criterion).__name__
    record["optimizer"] = type(trainer.optimizer).__name__
    stage(record, "Trainer built (dataloader, loss, NSSV1Model, optimizer, schedule)", t0)
    batch = next(iter(trainer.train_dataloader))
    record["batch"] = shapes(batch)
    stage(record, "one batch of the export", t0)
    return trainer, batch


def run(args, record: dict) -> int:
    t0 = time.perf_counter()
    args.work.mkdir(parents=True, exist_ok=True)
    trainer, batch = prepare(args, record, t0)
    trainer.model.train()
    if args.compile_slang:
        compile_slang(trainer, record)
    record["loss_before"] = batch_loss(trainer, batch, args.seed)
    stage(record, "forward and loss (the Slang module built on first use)", t0)
    record.update(one_step(trainer, batch, args.seed))
    stage(record, "one optimizer step", t0)
    record["loss_after"] = batch_loss(trainer, batch, args.seed)
    stage(record, "forward and loss after the step", t0)
    print(f"NSS-v1 one step on {record['device']}: loss {record['loss_before']:.6f} -> {record['loss_after']:.6f} "
          f"(in the step {record['loss_in_step']:.6f}), lr {record['lr']:g}, grad norm {record['grad_norm']:.4g}, "
          f"{record['parameter_tensors_changed']}/{record['parameter_tensors']} parameter tensors changed "
          f"(max |delta| {record['max_abs_parameter_change']:.3g})")
    finite = all(map(lambda v: v == v and abs(v) != float("inf"), (record["loss_before"], record["loss_after"])))
    return 0 if finite and record["grads_finite"] and record["parameter_tensors_changed"] > 0 else 1


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("safetensors", type=Path, help="the folder Arm's converter wrote (NNNN.safetensors)")
    p.add_argument("work", type=Path, help="a scratch folder: the config, checkpoints and output go there")
    p.add_argument("--recurrent-samples", type=int, default=4, help="frames per training window (default 4)")
    p.add_argument("--seed", type=int, default=123456)
    p.add_argument("--compile-slang", action="store_true",
                   help="build the Slang module before the forward (a diagnosis where CUDA is missing)")
    p.add_argument("--json", type=Path, help="write the record here")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from importlib.metadata import version

    record = {"ng_model_gym": version("ng-model-gym"), "torch": torch.__version__,
              "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None, "stages": []}
    rc = 1
    try:
        rc = run(args, record)
    except Exception as e:
        refused = isinstance(e, RuntimeError) and CUDA_REFUSAL in str(e)
        record["blocked" if refused else "error"] = f"{type(e).__name__}: {e}"[:2000]
        if not refused:
            raise
        print(f"BLOCKED at the forward on {record.get('device')}: {e} (every stage before it ran)")
        rc = 3
    finally:
        record["exit"] = rc
        if args.json:
            write_json_atomic(args.json, record)
    return rc


if __name__ == "__main__":
    sys.exit(main())
