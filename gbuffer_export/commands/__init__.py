"""The core's command modules (``blendsr render``, ``dataset``, ...): each parses arguments and calls a library
function. ``flags_named`` is where a command line puts its flags into the library's messages."""
from __future__ import annotations

import contextlib
import re


def flag_message(exc, args) -> str | None:
    """The message of the ConfigError ``exc`` with its key (``exc.key``, e.g. ``hr_size``; its first mention as a
    word) written as the flag that set it (``--hr-size``) when ``args`` (the parsed command line) has that flag;
    None when it has none."""
    key = getattr(exc, "key", None)
    if not key or key not in vars(args):
        return None
    flag = "--" + key.replace("_", "-")
    return re.sub(rf"(?<![\w./-]){re.escape(key)}(?![\w/-])", flag, str(exc), count=1)


@contextlib.contextmanager
def flags_named(args):
    """Re-raise a ConfigError (or SpecError) about a key the command line sets as the same error naming its flag."""
    from ..typed_table import ConfigError
    try:
        yield
    except ConfigError as exc:
        text = flag_message(exc, args)
        if text is None:
            raise
        raise type(exc)(text, key=exc.key, detail=exc.detail) from None
