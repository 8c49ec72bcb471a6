"""One dataset clip rendered by the Blender application (``build.job_command`` with a Blender executable)::

    blender --background --factory-startup --python dataset_job_script.py -- JOB.json CLIP_DIR [--threads N]

Inside Blender, ``sys.executable`` is Blender's bundled Python, which cannot import bpy, so the dataset executor
cannot start ``python -m gbuffer_export.blender.dataset_job`` there. This script puts the library on ``sys.path``
(the folder holding ``gbuffer_export``, and the site directories listed in ``$BLENDSR_SITE_DIRS``, separated by
``os.pathsep``: Blender ignores ``$PYTHONPATH`` unless started with ``--python-use-system-env``) and runs
``dataset_job.main`` on the arguments after ``--``. Standard library only until the paths are set.
"""
from __future__ import annotations

import os
import site
import sys


def library_paths(environ=os.environ) -> list[str]:
    """Folders to add: ``$BLENDSR_SITE_DIRS`` entries, then the folder holding this package."""
    dirs = [d for d in environ.get("BLENDSR_SITE_DIRS", "").split(os.pathsep) if d]
    here = os.path.dirname(os.path.abspath(__file__))
    return dirs + [os.path.dirname(os.path.dirname(here))]


def script_args(argv: list[str]) -> list[str]:
    """The arguments after ``--`` (Blender's convention), else everything after the script."""
    return argv[argv.index("--") + 1:] if "--" in argv else argv[1:]


def main(argv: list[str]) -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != here]  # no 'gbuffer_export.blender'
    for d in library_paths():                                                        # modules as top-level names
        if d not in sys.path:
            site.addsitedir(d)
            sys.path.remove(d)
            sys.path.insert(0, d)
    from gbuffer_export.blender.dataset_job import main as job_main
    return job_main(script_args(argv))


if __name__ == "__main__":
    code = main(sys.argv)
    sys.stdout.flush()
    sys.stderr.flush()
    if code:  # on success return normally: Blender in background mode then quits with status 0
        sys.exit(code)
