"""Issue 57 item 6: the README's first spec (three lines, your own .blend) works as shown, and docs/index.md lists
every docs page on one screen."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys

import pytest

from tests.conftest import ENV, REPO, shared_or_skip


def first_spec() -> str:
    """The first fenced block of the README's quick start that holds a [[source]] table."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    start = text.index("## Quick start")
    blocks = re.findall(r"```\n(.*?)```", text[start:], flags=re.S)
    spec = next(b for b in blocks if "[[source]]" in b)
    assert text.index(spec, start) < text.index("make demo", start), "the own-scene spec comes first"
    return spec


def _readme_dry_run(tmp_path, *extra: str) -> tuple[subprocess.CompletedProcess, int]:
    """The README's spec beside a copy of the garage, under the README's file name, and its ``dataset --dry-run``
    command (with ``extra``): (the finished process, the count of clips the README claims)."""
    spec = first_spec()
    assert len(spec.strip().splitlines()) == 3, spec
    blend = shared_or_skip("scenes/levels/garage/garage.blend")
    name = re.search(r'paths = \["([^"]+)"\]', spec).group(1)
    shutil.copyfile(blend, tmp_path / name)
    (tmp_path / "my_spec.toml").write_text(spec)
    proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "dataset", str(tmp_path / "my_spec.toml"),
                           "-o", str(tmp_path / "ds"), "--dry-run", *extra], cwd=tmp_path, env=ENV,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    clips = [ln for ln in proc.stdout.splitlines() if "camera=" in ln]
    readme = (REPO / "README.md").read_text()
    claimed = int(re.search(r"--dry-run +# lists the clips it plans \((\d+):", readme).group(1))
    assert len(clips) == claimed and {"camera=walk", "camera=fly"} <= {ln.split()[3] for ln in clips}, proc.stdout
    return proc, claimed


def test_the_readme_three_line_spec_lists_its_clips_on_a_blend(tmp_path):
    """The README's spec and command, the walk and fly paths not planned (``--no-plan``): it lists the clips the
    README claims. Planning on this level: tests/dataset/test_dry_run_plan.py, and the heavy test below."""
    proc, _ = _readme_dry_run(tmp_path, "--no-plan")
    assert "PATH " not in proc.stdout


@pytest.mark.heavy
def test_the_readme_three_line_spec_dry_runs_on_a_blend(tmp_path):
    """The README's command as written: every clip it lists gets a path in the garage with the spec's defaults
    (heavy: planning the default frame range's walk and fly paths takes about 45 s on 2 loaded cores)."""
    proc, claimed = _readme_dry_run(tmp_path)
    assert proc.stdout.splitlines()[-1] == f"blendsr: planned {claimed} walk/fly clips: {claimed} have a path, 0 none"


def test_the_docs_index_lists_every_page_on_one_screen():
    index = (REPO / "docs" / "index.md").read_text(encoding="utf-8")
    linked = set(re.findall(r"\]\(([^)#]+\.md)\)", index))
    pages = {str(p.relative_to(REPO / "docs")) for p in (REPO / "docs").rglob("*.md")
             if "bench" not in p.relative_to(REPO / "docs").parts and p.name != "index.md"}
    assert pages - linked == set(), "docs/index.md misses these pages"
    assert all((REPO / "docs" / p).is_file() for p in linked if not p.startswith("..")), "a link leads nowhere"
    assert len(index.splitlines()) <= 45
