"""The fused HR stage's tests (``tests/train/hr_stage_cases.py``: the fused path against the fp32 reference, the
held bf16 weights, the Triton kernels under the interpreter and compiled for sm_90, the bench's --path check) run in
a Python process of their own. In a pytest worker that had run some of the evaluation tests before, compiling the
fused stage with torch.compile aborted the process (SIGABRT inside dynamo; not reproduced outside pytest, cause not
found yet): a fresh process keeps these tests independent of what ran before them."""
import subprocess
import sys

import pytest

from tests.conftest import ENV, REPO

pytest.importorskip("torch")


def _cases(marks: str) -> None:
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", marks,
                           "tests/train/hr_stage_cases.py"], cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=1500)
    tail = proc.stdout.strip().splitlines()[-1:] if proc.stdout.strip() else []
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-2000:]
    assert tail and " passed" in tail[0], proc.stdout[-2000:]


def test_fused_hr_stage_cases_in_a_process_of_their_own():
    """The quick cases: every guided model's fused stage eager against the reference, bf16 weights of the small
    networks, the path's refusals, the sm_90 compile, one Triton kernel launch under the interpreter."""
    _cases("not heavy")


@pytest.mark.heavy
def test_fused_hr_stage_heavy_cases_in_a_process_of_their_own():
    """The cases over a minute (``hr_stage_cases.heavy``): compiled stages (bf16 weights with the compiled stage
    included), the Triton interpreter on every spec, the shipped networks, the bench's paths side by side
    (``make test-heavy``)."""
    _cases("heavy")
