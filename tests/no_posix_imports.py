"""Run by tests/system/test_platforms.py in a fresh interpreter: ``python no_posix_imports.py REPO LOCK_DIR``.

Imports every module of BlendSR (gbuffer_export, training, blender_addon; a module whose optional extra is not
installed is skipped) as on a platform without fcntl (nor termios, resource, grp: Windows) and with /proc
unreadable (macOS, Windows: ``open``, ``os.open``, ``os.listdir`` and ``os.scandir`` refuse it); then uses the
cross-platform paths (available memory, peak memory, a folder lock). One ``FAIL`` line per failure, exit 1 if any."""
import builtins
import importlib
import io
import os
import pkgutil
import sys
import warnings

BLOCKED = {"fcntl", "termios", "resource", "grp"}


class Blocker:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked: not on this platform)", name=name)
        return None


for m in list(sys.modules):
    if m.split(".")[0] in BLOCKED:
        del sys.modules[m]
sys.meta_path.insert(0, Blocker())


def _is_proc(p) -> bool:
    try:
        s = os.fsdecode(p) if not isinstance(p, int) else ""
    except TypeError:
        return False
    s = os.path.abspath(s) if s else s
    return s == "/proc" or s.startswith("/proc/")


def _guard(real):
    def guarded(p, *a, **k):
        if _is_proc(p):
            raise PermissionError(13, "Permission denied", os.fsdecode(p))
        return real(p, *a, **k)
    return guarded


builtins.open = io.open = _guard(io.open)
os.open, os.listdir, os.scandir = _guard(os.open), _guard(os.listdir), _guard(os.scandir)
try:
    open("/proc/meminfo")
    print("FAIL /proc still readable")
except PermissionError:
    pass

sys.path.insert(0, sys.argv[1])
from gbuffer_export.extras import extra_of  # noqa: E402

skipped, failed, imported = [], [], 0
for pkg in ("gbuffer_export", "training", "blender_addon"):
    root = importlib.import_module(pkg)
    names = [pkg] + [m.name for m in pkgutil.walk_packages(root.__path__, pkg + ".")]
    for name in names:
        try:
            importlib.import_module(name)
            imported += 1
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.split(".")[0] in BLOCKED:
                failed.append(f"{name}: imports {exc.name}")
            elif exc.name and extra_of(exc.name):
                skipped.append(name)
            else:
                failed.append(f"{name}: {type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001
            failed.append(f"{name}: {type(exc).__name__}: {exc}")

for f in failed:
    print("FAIL", f, flush=True)
if failed:
    sys.exit(1)
from gbuffer_export.resources import available_memory, peak_rss_bytes  # noqa: E402
mem = available_memory()
if mem is not None and not isinstance(mem, int):
    failed.append(f"available_memory() = {mem!r}")
peak_rss_bytes()
from gbuffer_export.locks import FolderBusyError, FolderLock  # noqa: E402
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    with FolderLock(sys.argv[2], "busy"):
        try:
            FolderLock(sys.argv[2], "busy")
            failed.append("a second FolderLock was granted")
        except FolderBusyError:
            pass
for f in failed:
    print("FAIL", f)
print(f"imported {imported}, skipped {len(skipped)} (extras not installed), memory {mem}")
sys.exit(1 if failed else 0)
