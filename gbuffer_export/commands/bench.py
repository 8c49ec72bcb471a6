"""``blendsr bench KIND``: benchmarks (speed and accuracy targets live here, never in timed tests)."""
from __future__ import annotations

import argparse
import sys

#: The core's benchmarks: name -> module exposing add_arguments(parser) and run(args). Other layers add theirs
#: through the entry-point group ``blendsr.bench`` (the torch layer: models, loader; see pyproject.toml).
CORE_BENCHES = {
    "render": "gbuffer_export.commands.bench_render",
    "brdf": "gbuffer_export.commands.bench_brdf",
}


def register(sub) -> None:
    from ..cli import MissingModule, entry_modules, import_optional
    from ..extras import HelpFormatter
    p = sub.add_parser("bench", help="benchmarks: render cost, BRDF accuracy, models' speed against error, loader",
                       description="Benchmarks. Each prints a table and can save JSON; numbers are medians.",
                       formatter_class=HelpFormatter)
    bsub = p.add_subparsers(dest="bench", metavar="KIND")
    for name, modname in entry_modules("blendsr.bench", CORE_BENCHES).items():
        mod = import_optional(modname)
        if mod is None:
            continue
        if isinstance(mod, MissingModule):
            mod.add_stub(bsub, name)
            continue
        bp = bsub.add_parser(name, help=(mod.__doc__ or name).strip().splitlines()[0],
                             description=mod.__doc__, formatter_class=HelpFormatter)
        mod.add_arguments(bp)
        bp.set_defaults(func=mod.run)
    def no_kind(args) -> int:  # 'blendsr bench' alone: usage on stderr and exit 2, as argparse does for an error
        p.print_usage(sys.stderr)
        print(f"blendsr bench: error: choose a KIND: {', '.join(bsub.choices)}", file=sys.stderr)
        return 2
    p.set_defaults(func=no_kind)
