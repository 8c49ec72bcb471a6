"""Partial installs and help: every command checks its extra up front and names it in one line (exit 2), every
command is listed whatever is installed, and ``COMMAND --help`` shows each default once.

A partial install is simulated in a subprocess: the modules of the missing extras are set to None in sys.modules
before the CLI starts, so ``import torch`` raises ModuleNotFoundError and ``importlib.util.find_spec('torch')``
returns None, as in an environment without them (fast: no new virtual environment).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap

import pytest

from tests.conftest import REPO, builtin_spec
from gbuffer_export.extras import EXTRAS

RUN = ("import sys\n"
       "for m in sys.argv[1].split(','):\n"
       "    if m: sys.modules[m] = None  # blocked: import raises ModuleNotFoundError, find_spec returns None\n"
       "sys.argv = ['blendsr', *sys.argv[2:]]\n"
       "from gbuffer_export.cli import main\n"
       "sys.exit(main())\n")


def blendsr_without(extras, *args, tmp_path=None, pythonpath=()):
    """Run ``blendsr ARGS`` in a process where the modules of ``extras`` cannot be imported."""
    blocked = ",".join(m for e in extras for m in EXTRAS[e])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([*map(str, pythonpath), str(REPO)]))
    return subprocess.run([sys.executable, "-c", RUN, blocked, *map(str, args)], capture_output=True, text=True,
                          cwd=tmp_path or REPO, env=env, timeout=120)


def assert_names_extra(proc, extra: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert len(lines) == 1, proc.stderr[-2000:]
    assert f"install the [{extra}] extra: pip install '.[{extra}]'" in lines[0], lines[0]
    assert "Traceback" not in proc.stderr


#: [render] only: commands of the torch layer, each with arguments that parse
TRAIN_COMMANDS = [
    ("train", "--model", "fusesr", "-o", "run"),
    ("evaluate", "--model", "bicubic", "--data", "clip", "--json", "out.json"),
    ("upscale", "--model", "bicubic", "--clip", "clip", "-o", "up"),
    ("export", "--model", "bicubic", "--onnx", "m.onnx"),
    ("bench", "models"),
    ("bench", "loader"),
]


def test_help_lists_every_command_with_only_the_render_extra(tmp_path):
    proc = blendsr_without(("train", "export", "cluster"), "--help", tmp_path=tmp_path)
    assert proc.returncode == 0, proc.stderr
    for cmd in ("render", "dataset", "validate", "lut", "bench", "demo", "train", "evaluate", "upscale", "export"):
        assert f"\n    {cmd} " in proc.stdout, cmd
    proc = blendsr_without(("train", "export", "cluster"), "bench", "--help", tmp_path=tmp_path)
    for kind in ("render", "brdf", "models", "loader"):
        assert f"\n    {kind} " in proc.stdout, kind


@pytest.mark.parametrize("args", TRAIN_COMMANDS, ids=lambda a: "-".join(a[:2]) if a[0] == "bench" else a[0])
def test_render_only_install_names_the_train_extra(args, tmp_path):
    proc = blendsr_without(("train", "export", "cluster"), *args, tmp_path=tmp_path)
    assert_names_extra(proc, "train")
    assert not any(tmp_path.iterdir()), "nothing is written before the check"


def test_bench_brdf_needs_matplotlib_before_it_renders(tmp_path):
    proc = blendsr_without(("train", "export"), "bench", "brdf", "--out", "b", "--work", "w", tmp_path=tmp_path)
    assert_names_extra(proc, "train")
    assert "matplotlib" in proc.stderr
    assert not any(tmp_path.iterdir()), "nothing rendered or written before the check"


def test_train_only_install_names_render_and_export(tmp_path):
    proc = blendsr_without(("render", "export"), "export", "--model", "bicubic", "--onnx", "m.onnx",
                           tmp_path=tmp_path)
    assert_names_extra(proc, "export")
    assert "onnx" in proc.stderr
    proc = blendsr_without(("render",), "render", "-o", "clip", "--hr-size", "64x36", tmp_path=tmp_path)
    assert_names_extra(proc, "render")
    proc = blendsr_without(("render",), "bench", "render", tmp_path=tmp_path)
    assert_names_extra(proc, "render")
    proc = blendsr_without(("render",), "demo", "-o", "d", tmp_path=tmp_path)
    assert_names_extra(proc, "render")
    proc = blendsr_without(("render",), "bench", "brdf", tmp_path=tmp_path)
    assert_names_extra(proc, "render")
    proc = blendsr_without(("render",), "dataset", REPO / "examples" / "dataset_small.toml", "-o", "ds",
                           tmp_path=tmp_path)
    assert_names_extra(proc, "render")
    proc = blendsr_without(("cluster",), "dataset", REPO / "examples" / "dataset_small.toml", "-o", "ds",
                           "--executor", "ray", tmp_path=tmp_path)
    assert_names_extra(proc, "cluster")
    assert not (tmp_path / "ds").exists() and not (tmp_path / "d").exists()


def test_a_plugin_command_importing_a_missing_extra_is_listed_and_names_it(tmp_path):
    """Another package's command module that imports torch at module level: listed, and running it says which
    extra to install (instead of vanishing from --help)."""
    (tmp_path / "torch_cmd.py").write_text("import torch\n\ndef register(sub):\n    pass\n")
    dist = tmp_path / "torch_cmd-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: torch-cmd\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[blendsr.commands]\ntorchy = torch_cmd\n")
    proc = blendsr_without(("train",), "--help", tmp_path=tmp_path, pythonpath=[tmp_path])
    assert "\n    torchy " in proc.stdout and "[train]" in proc.stdout
    proc = blendsr_without(("train",), "torchy", "--anything", tmp_path=tmp_path, pythonpath=[tmp_path])
    assert_names_extra(proc, "train")


def test_a_late_import_of_an_extra_is_one_line():
    from gbuffer_export.extras import missing_module_message
    assert "[export]" in missing_module_message(ModuleNotFoundError("x", name="onnxruntime"))
    assert missing_module_message(ModuleNotFoundError("x", name="nosuchthing")) is None


# ------------------------------------------------------------------------------------------------------ help
def _subcommands():
    from gbuffer_export.cli import build_parser
    parser = build_parser()
    out = []

    def walk(p, path):
        subs = [a for a in p._actions if a.__class__.__name__ == "_SubParsersAction"]
        if path:
            out.append((path, p))
        for a in subs:
            for name, sp in a.choices.items():
                walk(sp, [*path, name])
    walk(parser, [])
    return out


def _option_entries(text: str) -> list[str]:
    """The help text of each option: its first line (two spaces, then the flags) and the indented lines below."""
    entries, cur = [], None
    for line in text.splitlines():
        if re.match(r"^  \S", line):
            cur = [line]
            entries.append(cur)
        elif cur is not None and re.match(r"^\s{3,}\S", line):
            cur.append(line)
        else:
            cur = None
    return [" ".join(s.strip() for s in e) for e in entries]


#: a statement of a default in help text ("(default: X)", "(default X)", "default: X", "default is X", "defaults to
#: X"); counted without overlap, so "(default: X)" counts once
STATES_DEFAULT = re.compile(r"\(default\b|\bdefault\s*:|\bdefault is\b|\bdefaults? to\b", re.IGNORECASE)


def test_every_help_shows_each_default_once():
    """``blendsr --help`` and ``blendsr COMMAND [SUBCOMMAND] --help`` for every command the parser has: no option
    states its default twice, and none shows an empty one (None, [], '')."""
    from gbuffer_export.cli import build_parser
    commands = [([], build_parser()), *_subcommands()]
    names = {" ".join(p) for p, _ in commands}
    assert {"render", "dataset", "train", "evaluate", "export", "bench models", "bench brdf"} <= names
    bad = []
    for path, p in commands:
        for entry in _option_entries(p.format_help()):
            n = len(STATES_DEFAULT.findall(entry))
            if n > 1 or re.search(r"\(default: (None|\[\]|''|)\)", entry):
                bad.append(f"blendsr {' '.join(path)}: {entry}")
    assert not bad, "\n".join(bad)
    from gbuffer_export.extras import HelpFormatter
    plain = [" ".join(path) for path, p in commands[1:] if not issubclass(p.formatter_class, HelpFormatter)]
    assert not plain, f"commands whose --help shows no defaults (not extras.HelpFormatter): {plain}"


def test_the_help_check_catches_a_doubled_default():
    import argparse
    from gbuffer_export.extras import HelpFormatter
    p = argparse.ArgumentParser(formatter_class=HelpFormatter)
    p.add_argument("--a", default=3, help="a number; default is 3")
    p.add_argument("--b", default=4, help="b number (default: 4) (default: 4)")
    p.add_argument("--c", default=None, help="c (default: %(default)s)")
    flagged = [e for e in _option_entries(p.format_help())
               if len(STATES_DEFAULT.findall(e)) > 1 or re.search(r"\(default: (None|\[\]|''|)\)", e)]
    assert [e.split()[0] for e in flagged] == ["--b", "--c"]  # --a: the formatter appends nothing after "default is"


#: Every command of a [render]-only environment: those that work there, and (TRAIN_COMMANDS, bench brdf's chart)
#: those that stop naming [train]. A new command must be added to one of them (and tested there).
RENDER_ONLY_WORKS = {"render", "dataset", "validate", "preview", "lut", "bench render", "demo", "export-dataset",
                     "import-nss"}


def test_every_command_is_covered_for_the_render_only_environment():
    leaves = {" ".join(path) for path, p in _subcommands()
              if not any(a.__class__.__name__ == "_SubParsersAction" for a in p._actions)}
    named = {" ".join(a[:2]) if a[0] == "bench" else a[0] for a in TRAIN_COMMANDS} | {"bench brdf"}
    assert not RENDER_ONLY_WORKS & named
    assert leaves == RENDER_ONLY_WORKS | named, leaves ^ (RENDER_ONLY_WORKS | named)


@pytest.mark.parametrize("args", [("preview", "ds", "-o", "s.png"), ("export-dataset", "c", "--format", "nss",
                                                                     "-o", "n"), ("import-nss", "n", "-o", "c")],
                         ids=lambda a: a[0])
def test_core_commands_with_no_extra_never_ask_for_one(args, tmp_path):
    """preview, export-dataset and import-nss need no extra: missing input is a one-line usage error, not a hint to
    install something."""
    proc = blendsr_without(("render", "train", "export", "cluster"), *args, tmp_path=tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "extra" not in lines[0], proc.stderr[-2000:]


@pytest.mark.parametrize("kind", ["render", "brdf", "models", "loader"])
def test_bench_help_shows_defaults(kind):
    p = dict((" ".join(path), p) for path, p in _subcommands())[f"bench {kind}"]
    assert "(default: " in p.format_help()


def test_checkpoint_help_names_pretrained():
    helps = dict((" ".join(path), p.format_help()) for path, p in _subcommands())
    for cmd in ("evaluate", "upscale", "export"):
        assert "pretrained:NAME" in helps[cmd], cmd


def test_formatter_appends_a_default_only_when_the_help_has_none():
    import argparse
    from gbuffer_export.extras import HelpFormatter
    p = argparse.ArgumentParser(formatter_class=HelpFormatter)
    p.add_argument("--a", default=3, help="a number")
    p.add_argument("--b", default=None, help="omitted: the scene's")
    p.add_argument("--c", default="x", help="a letter (default: the first)")
    p.add_argument("--d", action="store_true", help="a flag")
    text = " ".join(p.format_help().split())
    assert "a number (default: 3)" in text
    assert "omitted: the scene's -" in text or text.count("default") == 2
    assert "(default: the first) --d" in text
    assert "default: False" not in text
    assert textwrap.dedent("").strip() == ""


def test_core_commands_work_without_any_extra(tmp_path):
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = make_synthetic_clip(tmp_path / "c", frames=(1, 2), hr_size=(64, 36))
    none = ("render", "train", "export", "cluster")
    proc = blendsr_without(none, "validate", clip, tmp_path=tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    proc = blendsr_without(none, "lut", "-o", "lut.exr", "--size", "8", "--samples", "16", "--workers", "1",
                           tmp_path=tmp_path)
    assert proc.returncode == 0 and (tmp_path / "lut.exr").is_file(), proc.stderr[-2000:]
    proc = blendsr_without(none, "dataset", builtin_spec(tmp_path / "spec.toml"), "-o", "ds", "--dry-run",
                           tmp_path=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_extras_table_matches_pyproject():
    """gbuffer_export.extras.EXTRAS names the import of every package of each extra in pyproject.toml (tomli-w
    aside: training.config falls back to its own writer without it, so its absence is no reason to stop)."""
    import tomllib
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    optional = {"tomli_w"}
    imports = {"cvvdp": "pycvvdp"}  # a distribution whose import has another name
    for extra, mods in EXTRAS.items():
        names = {re.split(r"[<>=!~\[ ;]", d, maxsplit=1)[0].strip().lower().replace("-", "_") for d in deps[extra]}
        assert {imports.get(n, n) for n in names} - optional == set(mods), extra
