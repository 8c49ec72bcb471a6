"""``blendsr lut``: compute the split-sum pre-integrated BRDF table and write it as an EXR (channels A and B)."""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from ..errors import BlendSRError

from ..extras import HelpFormatter

HELP = """Compute the split-sum table of the pre-integrated BRDF, F_beta = (1-m) c + F0 A(NoV, r) + B(NoV, r),
and write it as a float32 EXR with channels A and B.

Texel (row i, column j) of an N x N table holds the values at roughness (i + 0.5) / N and NoV = (j + 0.5) / N.
GGX importance sampling of a Hammersley set of S points per texel. Conventions: 'ibl' (Karis 2013: alpha =
roughness^2, Schlick-Smith k = alpha / 2; used by 'render --fbeta lut'), 'paper' (the NSRD supplement read
literally: alpha = roughness, k = (alpha + 1)^2 / 8; used by '--fbeta lut-paper'). See docs/brdf.md."""


def register(subparsers) -> None:
    p = subparsers.add_parser("lut", help="write the split-sum BRDF table (EXR, channels A and B)",
                              description=HELP, formatter_class=HelpFormatter)
    p.add_argument("-o", "--output", required=True, type=Path, help="EXR file to write (atomically)")
    p.add_argument("--size", type=int, default=256, help="table size N in texels per side (N x N)")
    p.add_argument("--samples", type=int, default=16384, help="Hammersley samples per texel")
    p.add_argument("--convention", choices=("ibl", "paper"), default="ibl",
                   help="alpha/k convention of the table (see above)")
    p.add_argument("--workers", type=int, default=None,
                   help="threads over roughness rows (default: the number of CPU cores)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..brdf import LutSpec, generate_lut, write_lut

    spec = LutSpec(size=args.size, samples=args.samples, convention=args.convention)
    if args.workers is not None and args.workers < 1:
        raise BlendSRError(f"--workers {args.workers}: must be >= 1")
    if args.output.suffix.lower() != ".exr":
        raise BlendSRError(f"{args.output}: output must be an .exr file")
    t0 = time.perf_counter()
    lut = generate_lut(spec, workers=args.workers)
    seconds = time.perf_counter() - t0
    write_lut(args.output, lut)
    print(f"wrote {args.output}: {spec.size}x{spec.size} {spec.convention} table, {spec.samples} samples/texel, "
          f"computed in {seconds:.2f} s; A in [{lut.a.min():.4f}, {lut.a.max():.4f}], "
          f"B in [{lut.b.min():.4f}, {lut.b.max():.4f}]")
    return 0
