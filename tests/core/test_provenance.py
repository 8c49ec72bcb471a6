"""``gbuffer_export.provenance``: the commit a frame record names (``commit``), read from git in a real repository
built here; None where git cannot say (no checkout tracking the package, no git, git failing or timing out); the
resume check of a clip's finished frames."""
from __future__ import annotations

import shutil
import subprocess

import pytest

from gbuffer_export import provenance

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(where, *args) -> str:
    """git in ``where`` without the caller's GIT_* variables (a hook's GIT_DIR would commit into this project)."""
    return subprocess.run(["git", "-C", str(where), "-c", "user.name=t", "-c", "user.email=t@t",
                           "-c", "commit.gpgsign=false", *args], check=True, capture_output=True, text=True,
                          env=provenance.git_env()).stdout.strip()


@pytest.fixture
def repo(tmp_path):
    pkg = tmp_path / "repo" / "pkg"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("x = 1\n")
    _git(pkg.parent, "init", "-q")
    _git(pkg.parent, "add", ".")
    _git(pkg.parent, "commit", "-q", "-m", "one")
    return pkg


@needs_git
def test_revision_is_the_commit_and_says_dirty(repo):
    head = _git(repo, "rev-parse", "HEAD")
    assert len(head) == 40 and provenance.revision_of(repo) == head
    (repo / "untracked.txt").write_text("not part of the code\n")
    assert provenance.revision_of(repo) == head  # an untracked file is not counted
    (repo / "__init__.py").write_text("x = 2\n")
    assert provenance.revision_of(repo) == head + "-dirty"
    _git(repo, "commit", "-q", "-am", "two")
    assert provenance.revision_of(repo) == _git(repo, "rev-parse", "HEAD") != head


@needs_git
def test_callers_git_variables_do_not_point_it_elsewhere(repo, tmp_path, monkeypatch):
    other = tmp_path / "other"
    other.mkdir()
    _git(other, "init", "-q")
    monkeypatch.setenv("GIT_DIR", str(other / ".git"))  # as inside a git hook of another repository
    assert provenance.revision_of(repo) == _git(repo, "rev-parse", "HEAD")


@needs_git
def test_no_revision_outside_a_checkout_that_tracks_the_package(repo, tmp_path, monkeypatch):
    (tmp_path / "loose").mkdir()
    (tmp_path / "loose" / "__init__.py").write_text("")
    assert provenance.revision_of(tmp_path / "loose") is None  # no repository
    ignored = repo.parent / "venv" / "pkg"  # an installed copy inside another repository's untracked folder
    ignored.mkdir(parents=True)
    (ignored / "__init__.py").write_text("")
    assert provenance.revision_of(ignored) is None
    monkeypatch.setattr(provenance.shutil, "which", lambda name: None)
    assert provenance.revision_of(repo) is None  # no git on the PATH


@needs_git
@pytest.mark.parametrize("failure", ["fails", "times out"])
def test_no_claim_when_git_cannot_tell_whether_the_tree_is_clean(repo, monkeypatch, failure):
    """A ``git status`` that fails or times out (a loaded machine) gives None, not the bare commit (a false clean)."""
    real = subprocess.run

    def run(cmd, **kw):
        if "status" in cmd:
            if failure == "times out":
                raise subprocess.TimeoutExpired(cmd, kw.get("timeout"))
            return subprocess.CompletedProcess(cmd, 128, "", "fatal")
        return real(cmd, **kw)
    monkeypatch.setattr(provenance.subprocess, "run", run)
    assert provenance.revision_of(repo) is None


def test_short_revision_keeps_the_dirty_mark():
    assert provenance.short_revision("a" * 40) == "a" * 12
    assert provenance.short_revision("b" * 40 + "-dirty") == "b" * 12 + "-dirty"


def test_a_resumed_clip_says_which_frames_other_code_rendered():
    now, old = "a" * 40, "b" * 40
    records = {3: {"commit": old}, 1: {"commit": now}, 2: {}, 4: {"commit": old}, 5: {"commit": now + "-dirty"}}
    assert provenance.other_code(records, now) == ("frames 2 by unrecorded code; frames 3, 4 by bbbbbbbbbbbb; "
                                                   "frames 5 by aaaaaaaaaaaa-dirty")
    assert provenance.other_code({1: {"commit": now}}, now) is None
    assert provenance.other_code({1: {}}, None) is None  # neither knows: nothing to say
