"""Ctrl-C while ``blendsr`` is still importing (before ``main`` runs) ends with one line and exit 130, no traceback
(issue 26: signals during render); importing the CLI module loads nothing slow and changes no signal handler."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, cwd=ROOT,
                          timeout=120)


def test_importing_the_cli_loads_neither_numpy_nor_openexr_and_keeps_the_signal_handler():
    r = _run("import signal, sys; h = signal.getsignal(signal.SIGINT); import gbuffer_export.cli; "
             "print(sorted({'numpy', 'OpenEXR'} & set(sys.modules)), signal.getsignal(signal.SIGINT) is h)")
    assert r.returncode == 0 and r.stdout.split() == ["[]", "True"], r.stdout + r.stderr


def test_ctrl_c_while_the_program_imports_is_one_line_and_exit_130():
    # As the console script: the handler is set at the CLI's import; a SIGINT in the middle of importing the
    # rest of BlendSR (numpy, OpenEXR, the commands) ends the process quietly.
    r = _run("import sys; sys.argv[0] = '/venv/bin/blendsr'; import gbuffer_export.cli; import os, signal; "
             "os.kill(os.getpid(), signal.SIGINT); import numpy, gbuffer_export.clip; print('not reached')")
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip() == "blendsr: interrupted" and "not reached" not in r.stdout


def test_ctrl_c_after_loading_is_keyboard_interrupt_again(tmp_path):
    # Once main() has parsed the command, Ctrl-C is a KeyboardInterrupt (a render stops between passes).
    p = subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "render", "-o", str(tmp_path / "c"),
                          "--hr-size", "64x36", "--frames", "1:40", "--lr-spp", "1", "--hr-spp", "1",
                          "--threads", "1"], env=ENV, cwd=ROOT, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120  # main() has parsed the command once the render holds its output folder
    while not (tmp_path / "c" / "manifest.json").is_file():
        assert p.poll() is None and time.monotonic() < deadline, p.stderr.read() if p.poll() is not None else ""
        time.sleep(0.1)
    p.send_signal(signal.SIGINT)
    err = p.communicate(timeout=120)[1]
    assert p.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
