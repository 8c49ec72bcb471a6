"""``gbuffer_export.provenance``: the commit a frame record names (``source``), read from git in a real repository
built here; None outside a checkout that tracks the package and without git."""
from __future__ import annotations

import shutil
import subprocess

import pytest

from gbuffer_export import provenance

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(where, *args) -> str:
    return subprocess.run(["git", "-C", str(where), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                          check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture
def repo(tmp_path):
    pkg = tmp_path / "repo" / "pkg"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("x = 1\n")
    _git(pkg.parent, "init", "-q")
    _git(pkg.parent, "add", ".")
    _git(pkg.parent, "commit", "-q", "-m", "one")
    return pkg


def test_revision_is_the_commit_and_says_dirty(repo):
    head = _git(repo, "rev-parse", "HEAD")
    assert len(head) == 40 and provenance.revision_of(repo) == head
    (repo / "untracked.txt").write_text("not part of the code\n")
    assert provenance.revision_of(repo) == head  # an untracked file is not a change of the code
    (repo / "__init__.py").write_text("x = 2\n")
    assert provenance.revision_of(repo) == head + "-dirty"
    _git(repo, "commit", "-q", "-am", "two")
    assert provenance.revision_of(repo) == _git(repo, "rev-parse", "HEAD") != head


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


def test_the_running_package_names_this_checkout():
    """The package under test names its checkout's HEAD, or None where it runs from a copy git does not track."""
    where = provenance.PACKAGE_DIR
    tracked = subprocess.run(["git", "-C", str(where), "ls-files", "--error-unmatch", "__init__.py"],
                             capture_output=True).returncode == 0
    head = subprocess.run(["git", "-C", str(where), "rev-parse", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    got = provenance.source_revision()
    assert (got.removesuffix("-dirty") if got else None) == (head if tracked else None)
