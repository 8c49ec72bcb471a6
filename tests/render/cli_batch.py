"""Several ``blendsr`` commands in one fresh Python process: bpy, trimesh and the library load once, not once per
command (about 5 s of start-up each on 2 busy cores). For tests that run a row of commands on tiny scenes, mostly
refusals; a test of the process itself (exit status of ``python -m gbuffer_export.cli``, Ctrl-C, the threads of
``--threads 1``) keeps ``tests.conftest.run_cli``.

Each command goes through ``gbuffer_export.cli.main(argv)``, as ``python -m gbuffer_export.cli`` calls it, with its
descriptors 1 and 2 sent to files of its own (Blender and Cycles write to the descriptors, not to ``sys.stderr``);
an argparse refusal's ``SystemExit`` is its exit status. Commands run in order; each one opens its own scene.

    python tests/render/cli_batch.py COMMANDS.json RESULTS.json   (a list of argument lists -> [{returncode,...}])
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def run_cli_batch(*argvs, timeout: int = 900) -> list[subprocess.CompletedProcess]:
    """Run ``blendsr ARGV`` for each ARGV in one child process; returns one completed process (text output) each."""
    from tests.conftest import ENV, REPO
    with tempfile.TemporaryDirectory(prefix="cli-batch-") as tmp:
        cmds, res = Path(tmp) / "commands.json", Path(tmp) / "results.json"
        cmds.write_text(json.dumps([[str(a) for a in argv] for argv in argvs]))
        proc = subprocess.run([sys.executable, str(Path(__file__)), str(cmds), str(res)], cwd=REPO, env=ENV,
                              capture_output=True, text=True, timeout=timeout)
        assert proc.returncode == 0 and res.is_file(), f"cli_batch exited {proc.returncode}:\n{proc.stderr[-3000:]}"
        return [subprocess.CompletedProcess(r["args"], r["returncode"], r["stdout"], r["stderr"])
                for r in json.loads(res.read_text())]


def make_blends(kinds, folder: Path) -> dict[str, Path]:
    """Build the fixtures ``kinds`` of tests/scenes.py as ``folder/KIND.blend`` in one process (``make_blend``
    builds one a process); returns kind -> path."""
    from tests.conftest import ENV, REPO, SCENES_SCRIPT
    paths = {k: Path(folder) / f"{k}.blend" for k in kinds}
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import scenes\n"
            "for k, p in zip(sys.argv[2::2], sys.argv[3::2]): scenes.main(k, p)")
    args = [str(a) for k, p in paths.items() for a in (k, p)]
    proc = subprocess.run([sys.executable, "-c", code, str(SCENES_SCRIPT.parent), *args], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and all(p.is_file() for p in paths.values()), proc.stderr[-2000:]
    return paths


def _run_one(argv: list[str], folder: Path, k: int) -> dict:
    from gbuffer_export.cli import main
    paths = folder / f"{k}.out", folder / f"{k}.err"
    saved = os.dup(1), os.dup(2)
    sys.stdout.flush(), sys.stderr.flush()
    with open(paths[0], "wb") as out, open(paths[1], "wb") as err:
        os.dup2(out.fileno(), 1), os.dup2(err.fileno(), 2)
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse's refusals; as the interpreter: None is 0, a message goes to stderr
            if exc.code is None or isinstance(exc.code, int):
                rc = exc.code or 0
            else:
                print(exc.code, file=sys.stderr)
                rc = 1
        finally:
            sys.stdout.flush(), sys.stderr.flush()
            os.dup2(saved[0], 1), os.dup2(saved[1], 2)
            os.close(saved[0]), os.close(saved[1])
    text = [p.read_text(errors="replace") for p in paths]
    return {"args": ["blendsr", *argv], "returncode": rc, "stdout": text[0], "stderr": text[1]}


def _main(commands: str, results: str) -> None:
    argvs = json.loads(Path(commands).read_text())
    with tempfile.TemporaryDirectory(prefix="cli-batch-io-") as tmp:
        out = [_run_one(argv, Path(tmp), k) for k, argv in enumerate(argvs)]
    Path(results).write_text(json.dumps(out))


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    _main(sys.argv[1], sys.argv[2])
