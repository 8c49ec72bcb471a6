"""The model gym step's helpers that run without the model gym: the stand-in modules (benchmarks/ngmg_stubs) and
the shell scripts' syntax. The step itself needs ng-model-gym and CUDA (benchmarks/gpu/nss_gym_step.sh)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import REPO

STUBS = REPO / "benchmarks" / "ngmg_stubs"
SCRIPTS = ["benchmarks/check_nss_consumer.sh", "benchmarks/gpu/nss_gym_step.sh", "benchmarks/gpu/fetch_nss_gym.sh",
           "benchmarks/gpu/check.sh"]


def run_python(code: str, stubs: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(STUBS), NGMG_STUBS=stubs)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)


def test_the_stand_ins_give_torchvisions_alexnet_stack_and_flips():
    code = """
import torch
from torchvision import models as tv
import torchvision.transforms.functional as F
import executorch.exir, pyiqa
convs = [m for m in tv.alexnet(pretrained=False).features if isinstance(m, torch.nn.Conv2d)]
print([c.out_channels for c in convs], [c.kernel_size[0] for c in convs])
x = torch.arange(24.0).reshape(1, 2, 3, 4)
assert torch.equal(F.hflip(x), x.flip(-1)) and torch.equal(F.vflip(x), x.flip(-2))
try:
    tv.alexnet(pretrained=True)
except RuntimeError as e:
    print("refused:", e)
"""
    proc = run_python(code, "executorch torchvision pyiqa")
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert lines[0] == "[64, 192, 384, 256, 256] [11, 5, 3, 3, 3]"  # torchvision's AlexNet.features
    assert lines[1].startswith("refused: torchvision is stubbed")


def test_only_the_named_modules_are_stubbed():
    proc = run_python("import sitecustomize, importlib.util as u; print(sitecustomize.STUBBED, "
                      "u.find_spec('torch').origin is not None)", "executorch pyiqa")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "('executorch', 'pyiqa') True"
    proc = run_python("import torchvision", "executorch")
    assert "sitecustomize" not in proc.stderr  # a real import (it may fail against this torch), not the stand-in


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_scripts_parse(script):
    proc = subprocess.run(["bash", "-n", str(REPO / script)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
