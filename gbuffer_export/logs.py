"""Where the library's notes go (pure Python). Library modules log through ``logging.getLogger(__name__)`` and
never print notes; a process boundary (``blendsr``'s ``main``, a dataset job process) calls ``configure_logging``
once. Progress bars (tqdm on stderr) are not log records and are unchanged."""
from __future__ import annotations

import contextlib
import logging
import sys

#: ``-q`` -> WARNING, default -> INFO, ``-v`` -> DEBUG.
LEVELS = {-1: logging.WARNING, 0: logging.INFO, 1: logging.DEBUG}


class StderrHandler(logging.StreamHandler):
    """Plain message lines on the current ``sys.stderr`` (looked up at each record, so a replaced stream, as
    tests and the add-on's workers use, receives them)."""

    def __init__(self):
        super().__init__()
        self.setFormatter(logging.Formatter("%(message)s"))

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it; sys.stderr is always used
        pass


def configure_logging(verbosity: int = 0) -> None:
    """The root logger at ``LEVELS[verbosity]`` (clamped to -1..1) with one ``StderrHandler``; other handlers (a
    test's log capture) are kept. Calling it again replaces the level and the handler."""
    root = logging.getLogger()
    for h in [h for h in root.handlers if isinstance(h, StderrHandler)]:
        root.removeHandler(h)
    root.addHandler(StderrHandler())
    root.setLevel(LEVELS[max(-1, min(1, int(verbosity)))])


@contextlib.contextmanager
def stderr_logging(verbosity: int = 0):
    """``configure_logging`` for the duration of a command; the root logger's level and handlers are restored after
    (``blendsr``'s ``main`` may run in-process, e.g. from tests or ``blendsr demo``)."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    configure_logging(verbosity)
    try:
        yield
    finally:
        for h in [h for h in root.handlers if h not in handlers]:
            root.removeHandler(h)
        for h in handlers:
            if h not in root.handlers:
                root.addHandler(h)
        root.setLevel(level)
