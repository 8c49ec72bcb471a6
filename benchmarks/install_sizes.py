"""Disk size of each extra of pyproject.toml, measured on an installed environment (README, "Installing without make").

    .venv/bin/python benchmarks/install_sizes.py [-o docs/bench/install-sizes/sizes.json]

For every extra: the distributions its requirements pull in, transitively (markers evaluated on this machine, with
the extra's name), read from pyproject.toml for blendsr itself and from ``importlib.metadata`` for every installed
distribution; each distribution's size is the sum of its files as its RECORD lists them (``Distribution.files``:
what pip installed; byte code Python writes later is not counted). An extra's size is what it adds to the base
install (``pip install .``); a distribution that is not installed here is listed under ``missing`` (not counted).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def dist_size(name: str) -> int | None:
    """Bytes of the files of the installed distribution ``name`` (None: not installed)."""
    try:
        dist = metadata.distribution(name)
    except metadata.PackageNotFoundError:
        return None
    total = 0
    for f in dist.files or []:
        p = Path(dist.locate_file(f))
        if p.is_file():
            total += p.stat().st_size
    return total


def closure(reqs: list[str], extras_of_self: dict[str, list[str]], extra: str = "") -> tuple[set[str], set[str]]:
    """(installed distributions, missing ones) that ``reqs`` pull in; ``blendsr[x]`` expands to its extras."""
    seen, missing, todo = set(), set(), [(r, extra) for r in reqs]
    while todo:
        text, ex = todo.pop()
        req = Requirement(text)
        if req.marker is not None and not req.marker.evaluate({"extra": ex}):
            continue
        name = _norm(req.name)
        if name == "blendsr":
            for e in req.extras:
                todo += [(r, e) for r in extras_of_self[e]]
            continue
        if name in seen or name in missing:
            continue
        try:
            dist = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            missing.add(name)
            continue
        seen.add(name)
        wanted = set(req.extras)
        for sub in dist.requires or []:
            r = Requirement(sub)
            if r.marker is None or r.marker.evaluate({"extra": ""}) or any(
                    r.marker.evaluate({"extra": e}) for e in wanted):
                todo.append((sub, ""))
    return seen, missing


def measure() -> dict:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    base, base_missing = closure(project["dependencies"], extras)
    sizes = {n: dist_size(n) or 0 for n in base}
    out = {"method": __doc__.split("\n\n")[1].replace("\n", " "), "python": sys.version.split()[0],
           "base": {"bytes": sum(sizes.values()), "largest": sorted(sizes.items(), key=lambda kv: -kv[1])[:6],
                    "distributions": sorted(base), "missing": sorted(base_missing)},
           "extras": {}}
    for name, reqs in extras.items():
        got, missing = closure(reqs, extras, name)
        added = got - base
        per = {n: dist_size(n) or 0 for n in added}
        out["extras"][name] = {"adds_bytes": sum(per.values()), "largest": sorted(per.items(), key=lambda kv: -kv[1])[:6],
                               "distributions": len(added), "missing": sorted(missing)}
    for n in ("torch", "triton", "bpy"):
        out.setdefault("single", {})[n] = {"version": _version(n), "bytes": dist_size(n)}
    return out


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--output", type=Path, help="write the JSON here")
    a = p.parse_args()
    res = measure()
    mb = 1e6
    print(f"base (pip install .): {res['base']['bytes'] / mb:.0f} MB")
    for name, e in res["extras"].items():
        top = ", ".join(f"{n} {b / mb:.0f}" for n, b in e["largest"][:3])
        miss = f"; not installed here: {', '.join(e['missing'])}" if e["missing"] else ""
        print(f"[{name}] adds {e['adds_bytes'] / mb:.0f} MB ({e['distributions']} distributions; largest MB: {top}){miss}")
    if a.output:
        a.output.parent.mkdir(parents=True, exist_ok=True)
        a.output.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
