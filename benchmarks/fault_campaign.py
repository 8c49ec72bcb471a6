"""Fault campaign: bad inputs, random inputs and SIGKILL + resume, counted.

    .venv/bin/python benchmarks/fault_campaign.py -o /tmp/faults [--kills 10] [--examples 40] [--quick] [--json F]

Parts (each prints its counts; the totals come last):

1. **Bad inputs** (``BAD_INPUTS``, table-driven): every command (render, validate, train, evaluate, upscale,
   export) on inputs a user gets wrong: missing/fake/non-.blend scenes, sizes that do not divide, absurd sizes,
   reversed frames, unknown buffers, output paths that are files or hold another clip, negative spp, truncated and
   random-byte EXRs, deleted frames, missing/corrupt/foreign manifests, NaN/Inf and 1e30 radiance, all-zero F_beta,
   unknown config keys, wrong types, unknown models, an existing run directory, non-checkpoint and malicious
   checkpoints... Each must exit with its expected code (2 for refused input), print a line containing
   ``error:`` when refused, and never a Python traceback.
2. **Random inputs** (hypothesis): random manifests (JSON mutations of a valid one), random EXRs (channel sets,
   dtypes, sizes) in place of a buffer, and random configuration TOML. ``validate_clip`` must return a report and
   ``load_config`` must raise ``ConfigError``/``ValueError`` or succeed; anything else counts as a traceback.
3. **SIGKILL + resume**: ``blendsr render`` (``--threads 1``) and ``blendsr train`` are killed with SIGKILL at
   random moments, rerun until they finish, and compared with an uninterrupted run: the clip must validate with every
   planned frame (0 corrupt clips, 0 lost frames), frames finished before a kill must not change afterwards, and
   the final weights must be bit-identical. Render frames (docs/clip-format.md, "Reproducibility"): the
   scene-determined buffers (depth, albedo, emission, motion, flags) must be bit-identical and the rest within 1e-6
   (normals, F_beta) or equal in the frame mean within 5% (radiance). Frames of the first (killed) process are
   counted when their radiance is also bit-identical to the uninterrupted run's (best effort on an idle machine);
   frames of a resumed process are another noise realisation.
4. **Add-on operators** (bpy): a missing checkpoint, a malicious checkpoint, an output folder that is a file and a
   scene without a camera each give an ERROR report, never a traceback.
5. **Concurrent writers**: a second ``ClipWriter`` of a clip (same settings, other settings before the first frame,
   the same shard, an unsharded writer beside shards, shards of another N) must be refused; with ``--races``: two
   ``blendsr render`` processes started together into one new folder (other seeds, then the same command) must give
   one exit 0 and one one-line exit 2, and a clip that validates with no ``mixed-clip`` finding; two shards together
   must fill one valid clip.
6. **Traversal and symlinks**: ``dataset.json`` clip paths that leave the dataset (``..``, absolute, through a link,
   empty, not a string) through ``validate`` (exit 1), ``train`` and ``evaluate`` (exit 2), and links inside a clip
   (a buffer, the manifest, ``frames/``, ``.blendsr_cache``; with ``--races`` a resumed render whose ``hr/radiance``
   is a link) must be refused, and nothing outside may be read or written (``escapes`` counts the failures).
7. **Signals during render** (``--signals N``): SIGINT (Ctrl-C, to the process group) at a random moment of a
   render must stop it with exit 130, no traceback, no partial frame and no temporary folder; the rerun must finish
   a clip that validates (each counts as a fault survived).
8. **Full filesystem**: the training cache on a 1 MB tmpfs (root mounts one; otherwise only the simulated case) and
   a simulated ENOSPC from ``posix_fallocate`` must stop training with one line (exit 2), no SIGBUS and no stray
   temporary file; a disk that fills while ``render`` or ``dataset`` writes (an 8 MB tmpfs filled after the first
   frame) must give a line naming the file and leave no temporary file.
9. **Huge specs and non-finite values** (``HUGE_AND_NONFINITE``, part ``huge``): specs of a million clips
   (seeds, clips per asset/scene), samples above Cycles' cap, inf/nan floats, a test asset in a train source, a
   million frames, an LR frame under 4 px: each refused in one line within ``RUNAWAY_S`` seconds; NaN/Inf in the
   ground truth or an LR input, and negative LR radiance, refused by ``evaluate`` (and ``train``) naming the file in
   validate's words; NaN/Inf in an LR input: ``upscale`` warns and writes finite EXRs. Issue 43's bad inputs: spec ``scales = []``, a spec key
   of the wrong type (the spec named once), ``regions = "axb"`` (echoed as written), ``preview --splits bogus``
   and ``--width 100000`` (checked against memory), ``--camera-path fly`` on a mesh of zero extent, and Ray
   addresses that are malformed, Ray Client or where nothing listens (a runaway before).
10. **Signals during a dataset** (part ``dsignals``, two rounds): SIGINT to the process group, then to the
   coordinator alone, after a dataset's first frame must stop it with exit 130 within ``DATASET_STOP_S`` (10 s),
   leave no clip process and start no further clip; the rerun must finish a dataset that validates.
11. **Scene files in a sandbox** (part ``sandbox``, issue 56, ``SANDBOX_CASES``): glTF buffer and image URIs and
   OBJ/MTL maps outside the scene's folder (``..``, absolute, through a link, ``/dev/zero``, a FIFO) and a .blend
   linking a library outside are refused in one line naming the file and the reference (an allowed folder is read
   and listed in the manifest); a crash or limit in an importer (truncated Alembic, Alembic garbage, a PLY of 4e9
   vertices, the time limit) is one line naming the file and the format; an FBX with a lamp imports; a glTF accessor
   count of 10^9 and a folder named ``s.glb`` are named; Ctrl-C during the import exits 130 with no clip.
12. **Exports** (part ``exports``): two ``export-dataset --append`` at once onto one export, for NSS, RDG and (not
   ``--quick``) NFRU on 1920x1080 clips, must both exit 0 with every sequence or scene listed once and none mixed;
   NFRU without a 2x level is refused naming NFRU; an NFRU export of a 64x36 clip (its reader loads 1920x1080) is
   refused before anything is written; ``import-nss`` of an NSS export validates.

13. **Frames with nothing in them, untrusted clips** (part ``empty``, issue 56, ``EMPTY_AND_UNTRUSTED``): a
   truncated OBJ (vertices, no faces), a truncated and a random-bytes STL, every vertex NaN, a PLY face naming a
   missing vertex, a zero-extent mesh and a 1e7 m level are refused by ``render`` before rendering in one line
   naming the file; a clip whose exposure was set x10 or 1e6, nulled or deleted in its manifest, or whose radiance
   was scaled by 1e-5, is refused by ``train``, ``evaluate``, ``upscale`` and ``export-dataset`` naming the
   failed check; the training cache rebuilds after an EXR changed under kept file times and ``train`` refuses an
   EXR become a link.

``--quick`` runs the subset ``tests/system/test_fault_campaign.py`` runs (``make test`` its cheap cases, ``make
test-heavy`` the families whose cost is the point). Exit code 0 when every count of failures is 0.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import random
import shutil
import signal
import struct
import subprocess
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

TRACEBACK = "Traceback (most recent call last)"
ENV = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
def render_args(frames: int) -> list[str]:
    return ["--hr-size", "64x36", "--frames", f"1:{frames}", "--hr-spp", "4", "--lr-spp", "2", "--seed", "3",
            "--threads", "1", "--no-progress"]
TRAIN_SETS = ["data.crop=8", "data.batch_size=2", "model.fusesr.width=8", "model.fusesr.blocks=1",
              "run.progress=false", "run.amp=\"none\"", "run.threads=1", "run.checkpoint_every=1", "run.log_every=1"]


@dataclass
class Tally:
    inputs_tried: int = 0
    tracebacks: int = 0
    wrong_exit: int = 0          # refused with another exit code than expected, or accepted when it must not be
    no_error_line: int = 0       # refused without a line saying 'error:'
    faults: int = 0              # SIGKILLs delivered
    faults_survived: int = 0     # kills after which the resumed run finished and checked out
    corrupt_clips: int = 0
    lost_frames: int = 0
    changed_frames: int = 0      # frames finished before a kill that changed afterwards
    results_compared: int = 0
    results_differ: int = 0      # final weights or first-process frames not bit-identical, or resumed frames off
    frames_bit_identical: int = 0  # render frames of a killed first process equal to the uninterrupted run's
    frames_resumed: int = 0      # render frames of resumed processes checked (see module doc)
    escapes: int = 0             # security failures: something outside a dataset or clip folder read or written
    failures: list = field(default_factory=list)

    def fail(self, what: str) -> None:
        self.failures.append(what)
        self.log(f"  FAIL {what}")

    log = staticmethod(lambda m: None)

    def bad(self) -> int:
        return (self.tracebacks + self.wrong_exit + self.no_error_line + self.corrupt_clips + self.lost_frames
                + self.changed_frames + self.results_differ + self.escapes + (self.faults - self.faults_survived))


# ------------------------------------------------------------------------------------------------------ fixtures
class Fixtures:
    """Files the bad inputs refer to, built once under ``root``."""

    def __init__(self, root: Path):
        from gbuffer_export.synthetic import make_synthetic_clip
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.clip = make_synthetic_clip(root / "clip", frames=range(1, 5), hr_size=(64, 36), scale=4)
        self.clip2 = make_synthetic_clip(root / "clip_x2", frames=range(1, 5), hr_size=(64, 36), scale=2)
        (root / "notes.txt").write_text("not a scene\n")
        (root / "fake.blend").write_text("BLENDER? no, text\n")
        (root / "random.bin").write_bytes(random.Random(0).randbytes(4096))
        (root / "a_file").write_text("I am a file\n")
        (root / "empty_dir").mkdir(exist_ok=True)
        self._variants: dict[str, Path] = {}
        self._ck: Path | None = None

    def variant(self, name: str, mutate, base: Path | None = None) -> Path:
        """A copy of the good clip (or of ``base``) changed by ``mutate(path)``."""
        if name not in self._variants:
            p = self.root / f"v_{name}"
            if p.exists():
                shutil.rmtree(p)
            shutil.copytree(base or self.clip, p, ignore=shutil.ignore_patterns(".blendsr_cache"))
            mutate(p)
            self._variants[name] = p
        return self._variants[name]

    def checkpoint(self) -> Path:
        """A real checkpoint (1 training step on the good clip)."""
        if self._ck is None:
            run = self.root / "run_ok"
            if not (run / "checkpoints" / "last.pt").is_file():
                argv = ["train", "--model", "fusesr", "--data", str(self.clip), "-o", str(run), "--max-steps", "1"]
                for s in TRAIN_SETS:
                    argv += ["--set", s]
                proc = cli(argv)
                if proc.returncode != 0:
                    raise RuntimeError(f"fixture training failed: {proc.stderr[-2000:]}")
            self._ck = run / "checkpoints" / "last.pt"
        return self._ck

    def malicious(self) -> Path:
        p = self.root / "evil.pt"
        if not p.exists():
            code = ("import os, torch\nclass P:\n    def __reduce__(self):\n        return (os.system, ('touch "
                    f"{self.root / 'PWNED'}',))\ntorch.save({{'format': 'blendsr.checkpoint', 'm': P()}}, '{p}')\n")
            subprocess.run([sys.executable, "-c", code], check=True, env=ENV, capture_output=True)
        return p


def _edit_exr(clip: Path, frame: int, key: str, fn) -> None:
    from gbuffer_export.clip import open_clip
    from gbuffer_export.exr import write_exr
    c = open_clip(clip)
    a = c.read(frame, key)
    a = fn(a)
    chans = {"radiance": "RGB", "fbeta": "RGB", "albedo": "RGB", "emission": "RGB"}[key.split("/")[1]]
    write_exr(c.path_of(frame, key), {ch: a[..., i] for i, ch in enumerate(chans)})


def _set(a, idx, v):
    a[idx] = v
    return a


def _path(clip: Path, frame: int, key: str) -> Path:
    from gbuffer_export.clip import open_clip
    return Path(open_clip(clip).path_of(frame, key))


def _truncate(clip):
    p = _path(clip, 2, "hr/normal")
    p.write_bytes(p.read_bytes()[:200])


def _random_bytes(clip):
    _path(clip, 2, "lr/radiance").write_bytes(random.Random(1).randbytes(3000))


def _delete_frame(clip):
    _path(clip, 3, "hr/radiance").unlink()


def _manifest(clip, fn):
    m = clip / "manifest.json"
    m.write_text(fn(m.read_text()))


def _foreign_manifest(text):
    return json.dumps({"schema": "someone.else", "frames": [1, 2]})


def _manifest_wrong_types(text):
    m = json.loads(text)
    m["scale"] = "four"
    m["levels"] = [1, 2]
    return json.dumps(m)


# ---------------------------------------------------------------------------------------------------- bad inputs
@dataclass
class BadInput:
    name: str
    argv: object                 # list of str, or callable(Fixtures) -> list of str
    expect: tuple = (2,)         # accepted exit codes
    quick: bool = False          # part of the make-test subset
    inproc: bool = True          # run in this process (fast); False: a fresh Python (render, bpy)


def _r(*a):
    return ["render", *a]


BAD_INPUTS: list[BadInput] = [
    # render (fresh process each: bpy)
    BadInput("render: missing scene", lambda f: _r(str(f.root / "nope.blend"), "-o", str(f.root / "o1")),
             quick=True, inproc=False),
    BadInput("render: fake .blend", lambda f: _r(str(f.root / "fake.blend"), "-o", str(f.root / "o2")),
             inproc=False),
    BadInput("render: not a .blend", lambda f: _r(str(f.root / "notes.txt"), "-o", str(f.root / "o3")),
             inproc=False),
    BadInput("render: size not divisible by scale", lambda f: _r("-o", str(f.root / "o4"), "--hr-size", "63x36"),
             inproc=False),
    BadInput("render: scale 0", lambda f: _r("-o", str(f.root / "o5"), "--scale", "0"), inproc=False),
    BadInput("render: reversed frames", lambda f: _r("-o", str(f.root / "o6"), "--frames", "4:1"), inproc=False),
    BadInput("render: unknown buffer", lambda f: _r("-o", str(f.root / "o7"), "--buffers", "radiance,glow"),
             inproc=False),
    BadInput("render: negative spp", lambda f: _r("-o", str(f.root / "o8"), "--hr-spp", "-4"), inproc=False),
    BadInput("render: zero LR spp", lambda f: _r("-o", str(f.root / "o9"), "--lr-spp", "0"), inproc=False),
    BadInput("render: absurd size", lambda f: _r("-o", str(f.root / "o10"), "--hr-size", "100000x100000",
                                                  "--frames", "1:1"), quick=True, inproc=False),
    BadInput("render: size not WxH", lambda f: _r("-o", str(f.root / "o11"), "--hr-size", "big"), inproc=False),
    BadInput("render: bad shard", lambda f: _r("-o", str(f.root / "o12"), "--shard", "3/2"), inproc=False),
    BadInput("render: output holds another clip", lambda f: _r("-o", str(f.clip), "--hr-size", "64x36",
                                                               "--frames", "1:1", "--hr-spp", "1"), inproc=False),
    BadInput("render: output is a file", lambda f: _r("-o", str(f.root / "a_file"), "--hr-size", "64x36",
                                                      "--frames", "1:1", "--hr-spp", "1"), inproc=False),
    BadInput("render: unknown camera path", lambda f: _r("-o", str(f.root / "o13"), "--camera-path", "fly"),
             inproc=False),
    BadInput("render: negative bounces", lambda f: _r("-o", str(f.root / "o14"), "--max-bounces", "-1",
                                                      "--hr-size", "64x36", "--frames", "1:1"), inproc=False),
    BadInput("render: negative threads", lambda f: _r("-o", str(f.root / "o15"), "--threads", "-2",
                                                      "--hr-size", "64x36", "--frames", "1:1"), inproc=False),
    BadInput("render: frames not A:B", lambda f: _r("-o", str(f.root / "o16"), "--frames", "one"), inproc=False),
    BadInput("render: unknown fbeta source", lambda f: _r("-o", str(f.root / "o17"), "--fbeta", "guess"),
             inproc=False),
    # validate
    BadInput("validate: missing clip", lambda f: ["validate", str(f.root / "nope")], expect=(1, 2), quick=True),
    BadInput("validate: folder without manifest", lambda f: ["validate", str(f.root / "empty_dir")], expect=(1, 2)),
    BadInput("validate: clip is a file", lambda f: ["validate", str(f.root / "a_file")], expect=(1, 2)),
    BadInput("validate: corrupt manifest",
             lambda f: ["validate", str(f.variant("corrupt_manifest", lambda c: _manifest(c, lambda t: t[:-40])))],
             expect=(1, 2), quick=True),
    BadInput("validate: foreign manifest",
             lambda f: ["validate", str(f.variant("foreign", lambda c: _manifest(c, _foreign_manifest)))],
             expect=(1, 2)),
    BadInput("validate: manifest of wrong types",
             lambda f: ["validate", str(f.variant("types", lambda c: _manifest(c, _manifest_wrong_types)))],
             expect=(1, 2)),
    BadInput("validate: truncated EXR", lambda f: ["validate", str(f.variant("trunc", _truncate))], expect=(1,),
             quick=True),
    BadInput("validate: random-byte EXR", lambda f: ["validate", str(f.variant("randexr", _random_bytes))],
             expect=(1,)),
    BadInput("validate: deleted frame", lambda f: ["validate", str(f.variant("deleted", _delete_frame))],
             expect=(1,)),
    BadInput("validate: NaN radiance", lambda f: ["validate", str(f.variant(
        "nan", lambda c: _edit_exr(c, 2, "lr/radiance", lambda a: _set(a, (1, 1, 0), float("nan")))))],
        expect=(1,)),
    BadInput("validate: 1e30 radiance (warning)", lambda f: ["validate", str(f.variant(
        "huge", lambda c: _edit_exr(c, 2, "lr/radiance", lambda a: _set(a, (1, 1, 0), 1e30))))], expect=(0,),
        quick=True),
    BadInput("validate: manifest is a folder", lambda f: ["validate", str(f.variant(
        "mdir", lambda c: ((c / "manifest.json").unlink(), (c / "manifest.json").mkdir())))], expect=(1, 2)),
    # train
    BadInput("train: unknown config key", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), "-o",
                                                     str(f.root / "t1"), "--set", "data.bogus=1"], quick=True),
    BadInput("train: wrong type", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), "-o",
                                             str(f.root / "t2"), "--set", "data.crop=\"big\""]),
    BadInput("train: unknown option of the model", lambda f: [
        "train", "--model", "fusesr", "--data", str(f.clip), "-o", str(f.root / "t2b"), "--set", "model.fusesr.zap=1"]),
    BadInput("train: --set without =", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), "-o",
                                                  str(f.root / "t3"), "--set", "data.crop"]),
    BadInput("train: unknown model", lambda f: ["train", "--model", "srgan9000", "--data", str(f.clip), "-o",
                                                str(f.root / "t4")], quick=True),
    BadInput("train: untrainable model", lambda f: ["train", "--model", "bicubic", "--data", str(f.clip), "-o",
                                                    str(f.root / "t5")]),
    BadInput("train: no data", lambda f: ["train", "--model", "fusesr", "-o", str(f.root / "t6")]),
    BadInput("train: missing clip", lambda f: ["train", "--model", "fusesr", "--data", str(f.root / "nope"), "-o",
                                               str(f.root / "t7")]),
    BadInput("train: folder that is not a clip", lambda f: ["train", "--model", "fusesr", "--data",
                                                            str(f.root / "empty_dir"), "-o", str(f.root / "t8")]),
    BadInput("train: existing run directory", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), "-o",
                                                         str(f.checkpoint().parents[1]), "--max-steps", "1"]),
    BadInput("train: resume without a run", lambda f: ["train", "-o", str(f.root / "t9"), "--resume"]),
    BadInput("train: mixed scales", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), str(f.clip2),
                                               "-o", str(f.root / "t10")]),
    BadInput("train: crop larger than the clip", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip),
                                                            "-o", str(f.root / "t11"), "--set", "data.crop=48"]),
    BadInput("train: negative max steps", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), "-o",
                                                     str(f.root / "t12"), "--max-steps", "-3"]),
    BadInput("train: config file missing", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), "-o",
                                                      str(f.root / "t13"), "--config", str(f.root / "nope.toml")]),
    BadInput("train: config not TOML", lambda f: ["train", "--model", "fusesr", "--data", str(f.clip), "-o",
                                                  str(f.root / "t14"), "--config", str(f.root / "random.bin")]),
    BadInput("train: NaN radiance", lambda f: ["train", "--model", "fusesr", "--data", str(f.variant(
        "nan", lambda c: _edit_exr(c, 2, "lr/radiance", lambda a: _set(a, (1, 1, 0), float("nan"))))), "-o",
        str(f.root / "t15"), "--max-steps", "1", "--set", "data.crop=8"]),
    BadInput("train: 1e30 radiance", lambda f: ["train", "--model", "fusesr", "--data", str(f.variant(
        "huge", lambda c: _edit_exr(c, 2, "lr/radiance", lambda a: _set(a, (1, 1, 0), 1e30)))), "-o",
        str(f.root / "t16"), "--max-steps", "1", "--set", "data.crop=8"], quick=True),
    BadInput("train: truncated EXR", lambda f: ["train", "--model", "fusesr", "--data", str(f.variant(
        "trunc", _truncate)), "-o", str(f.root / "t17"), "--max-steps", "1", "--set", "data.crop=8"]),
    BadInput("train: deleted frame", lambda f: ["train", "--model", "fusesr", "--data", str(f.variant(
        "deleted", _delete_frame)), "-o", str(f.root / "t18"), "--max-steps", "1", "--set", "data.crop=8"]),
    BadInput("train: all-zero fbeta (eps floor; trains)", lambda f: [
        "train", "--model", "fusesr", "--data", str(f.variant("zero_fbeta", lambda c: [
            _edit_exr(c, fr, f"{lv}/fbeta", lambda a: a * 0) for fr in range(1, 5) for lv in ("hr", "lr")])),
        "-o", str(f.root / "t19"), "--max-steps", "1", *sum((["--set", s] for s in TRAIN_SETS), [])], expect=(0,)),
    # evaluate / upscale / export
    BadInput("evaluate: missing checkpoint", lambda f: ["evaluate", "--checkpoint", str(f.root / "nope.pt"),
                                                        "--data", str(f.clip), "--json", str(f.root / "e1.json")]),
    BadInput("evaluate: not a checkpoint", lambda f: ["evaluate", "--checkpoint", str(f.root / "random.bin"),
                                                      "--data", str(f.clip), "--json", str(f.root / "e2.json")],
             quick=True),
    BadInput("evaluate: text file as checkpoint", lambda f: ["evaluate", "--checkpoint", str(f.root / "notes.txt"),
                                                             "--data", str(f.clip), "--json",
                                                             str(f.root / "e3.json")]),
    BadInput("evaluate: malicious checkpoint", lambda f: ["evaluate", "--checkpoint", str(f.malicious()), "--data",
                                                          str(f.clip), "--json", str(f.root / "e4.json")],
             quick=True),
    BadInput("evaluate: checkpoint of another scale", lambda f: ["evaluate", "--checkpoint", str(f.checkpoint()),
                                                                 "--data", str(f.clip2), "--json",
                                                                 str(f.root / "e5.json"), "--no-flip"]),
    BadInput("evaluate: unknown model", lambda f: ["evaluate", "--model", "magic", "--data", str(f.clip), "--json",
                                                   str(f.root / "e6.json")]),
    BadInput("evaluate: missing clip", lambda f: ["evaluate", "--model", "bilinear", "--data", str(f.root / "nope"),
                                                  "--json", str(f.root / "e7.json")]),
    BadInput("evaluate: frames outside the clip", lambda f: ["evaluate", "--model", "bilinear", "--data",
                                                             str(f.clip), "--json", str(f.root / "e8.json"),
                                                             "--frames", "7:9", "--no-flip"]),
    BadInput("evaluate: unknown model key", lambda f: ["evaluate", "--model", "demod-jbu", "--data", str(f.clip),
                                                       "--json", str(f.root / "e9.json"), "--set", "model.zap=1"]),
    BadInput("upscale: output is a file", lambda f: ["upscale", "--checkpoint", str(f.checkpoint()), "--clip",
                                                     str(f.clip), "-o", str(f.root / "a_file")]),
    BadInput("upscale: malicious checkpoint", lambda f: ["upscale", "--checkpoint", str(f.malicious()), "--clip",
                                                         str(f.clip), "-o", str(f.root / "u2")]),
    BadInput("export: not a checkpoint", lambda f: ["export", "--checkpoint", str(f.root / "random.bin"), "--onnx",
                                                    str(f.root / "x.onnx")]),
]


def cli(argv, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gbuffer_export.cli", *argv], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=timeout)


def run_inproc(argv) -> tuple[int, str, bool]:
    """``main(argv)`` in this process: (exit code, stderr, whether an exception escaped)."""
    from gbuffer_export.cli import main
    err = io.StringIO()
    escaped = False
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
        except Exception:
            escaped = True
            code = -1
            err.write(traceback.format_exc())
    return code, err.getvalue(), escaped


def bad_inputs(fx: Fixtures, tally: Tally, quick: bool, log=print) -> None:
    for case in BAD_INPUTS:
        if quick and not case.quick:
            continue
        argv = case.argv(fx) if callable(case.argv) else list(case.argv)
        if case.inproc:
            code, err, escaped = run_inproc(argv)
        else:
            proc = cli(argv, timeout=300)
            code, err, escaped = proc.returncode, proc.stderr, False
        tally.inputs_tried += 1
        problems = []
        if escaped or TRACEBACK in err:
            tally.tracebacks += 1
            problems.append("traceback")
        if code not in case.expect:
            tally.wrong_exit += 1
            problems.append(f"exit {code}, expected {case.expect}")
        if code == 2 and "error:" not in err:
            tally.no_error_line += 1
            problems.append("no 'error:' line")
        if problems:
            last = [ln for ln in err.strip().splitlines() if ln.strip()][-1:] or [""]
            tally.fail(f"{case.name}: {', '.join(problems)}: {last[0][:200]}")
        log(f"  {'FAIL' if problems else 'ok  '} {case.name}: exit {code}")
    if (fx.root / "PWNED").exists():
        tally.fail("the malicious checkpoint ran code")
        tally.tracebacks += 1


# ------------------------------------------------------------------- huge specs; non-finite values (issue 26)
#: A case must be answered within this many seconds (a runaway otherwise: counted as a wrong exit).
RUNAWAY_S = 60


def _spec_file(fx: Fixtures, name: str, source: str, render: str = "") -> Path:
    p = fx.root / f"{name}.toml"
    p.write_text(f'[dataset]\nname = "{name}"\n[render]\nhr_size = "64x36"\nframes = 2\n{render}'
                 f'[[source]]\n{source}')
    return p


def _asset_dir(fx: Fixtures) -> Path:
    d = fx.root / "assets"
    d.mkdir(exist_ok=True)
    (d / "Chair.gltf").write_text('{"asset": {"version": "2.0"}}')
    (d / "Lamp.gltf").write_text('{"asset": {"version": "2.0"}}')
    return d


def _ds(fx: Fixtures, name: str, source: str, render: str = "", extra=()) -> list[str]:
    return ["dataset", str(_spec_file(fx, name, source, render)), "-o", str(fx.root / f"ds_{name}"), "--dry-run",
            *extra]


def _sr_finite(out: Path) -> str | None:
    from gbuffer_export.exr import read_exr
    import numpy as np
    for f in sorted(out.glob("*.exr")):
        if not np.isfinite(read_exr(f, ("R", "G", "B"))).all():
            return f"{f} holds non-finite pixels"
    return None


def _eval_json_finite(path: Path) -> str | None:
    try:
        json.loads(path.read_text(), parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    except (OSError, ValueError) as exc:
        return f"{path}: {exc}"
    return None


def _preview_ds(fx: Fixtures) -> Path:
    """A dataset index of three 64x32 clips (no clip folders) for the ``preview`` cases."""
    d = fx.root / "preview_ds"
    if not (d / "dataset.json").is_file():
        d.mkdir(exist_ok=True)
        clips = [{"id": f"c{i}", "path": f"clips/c{i}", "split": "train", "state": "done", "frames_planned": 2,
                  "render": {"hr_size": [64, 32]}} for i in range(3)]
        (d / "dataset.json").write_text(json.dumps({"schema": "blendsr-dataset", "schema_version": 1, "name": "p",
                                                    "seed": 0, "splits": {}, "clips": clips}))
    return d


def _zero_extent_glb(fx: Fixtures) -> Path:
    """A glTF whose only mesh is one triangle collapsed to a point."""
    p = fx.root / "zero_extent.glb"
    if not p.is_file():
        import numpy as np
        import trimesh
        trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False).export(p)
    return p


def _free_port() -> int:
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ray(fx: Fixtures, name: str, address: str) -> list[str]:
    return ["dataset", str(_spec_file(fx, name, 'name = "b"\nkind = "builtin"\nseeds = "0:0"\n')), "-o",
            str(fx.root / f"ds_{name}"), "--executor", "ray", "--address", address, "--no-progress"]


def _names_once(path_of):
    """A check: the error names ``path_of(fx)`` exactly once."""
    return lambda f, code, err: (None if err.count(str(path_of(f))) == 1 else
                                 f"the error names {path_of(f)} {err.count(str(path_of(f)))} times")


def _says(*words):
    return lambda f, code, err: next((f"the error does not say {w!r}" for w in words if w not in err), None)


#: name, argv(fx), expected exit codes, quick, in-process, extra check(fx, code, stderr) -> problem or None.
HUGE_AND_NONFINITE = [
    # huge specs: refused in one line, at once (before anything is expanded, built or rendered)
    ("spec: a million builtin seeds", lambda f: _ds(f, "seeds1m", 'kind = "builtin"\nseeds = "0:999999"\n'),
     (2,), True, True, None),
    ("spec: a million clips per asset", lambda f: (_asset_dir(f), _ds(f, "cpa1m", 'kind = "assets"\npaths = '
                                                   '["assets"]\nclips_per_asset = 1000000\n'))[1],
     (2,), True, True, None),
    ("spec: a million clips per scene", lambda f: (_asset_dir(f), _ds(f, "cps1m", 'kind = "scene"\npaths = '
                                                   '["assets"]\nclips_per_scene = 1000000\n'))[1],
     (2,), False, True, None),
    ("spec: hr_spp above Cycles' cap", lambda f: _ds(f, "spp", 'kind = "builtin"\nseeds = "0:1"\n',
                                                       "hr_spp = 1000000000\n"), (2,), True, True, None),
    ("spec: hdri_strength = inf", lambda f: _ds(f, "inf", 'kind = "builtin"\nseeds = "0:1"\nhdri_strength = inf\n'),
     (2,), True, True, None),
    ("spec: target_size_m = nan", lambda f: (_asset_dir(f), _ds(f, "nan", 'kind = "assets"\npaths = ["assets"]\n'
                                                              'target_size_m = nan\n'))[1], (2,), False, True, None),
    ("spec: a test asset in a train source", lambda f: (_asset_dir(f), _ds(
        f, "leak", 'kind = "assets"\npaths = ["assets"]\nsplit = "train"\n', "[splits]\ntest = [\"Lamp\"]\n"))[1],
     (2,), True, True, None),
    ("render: a million frames", lambda f: _r("-o", str(f.root / "h1"), "--hr-size", "64x36", "--frames",
                                              "1:100000000", "--threads", "1"), (2,), True, False, None),
    ("render: a billion samples", lambda f: _r("-o", str(f.root / "h2"), "--hr-size", "64x36", "--frames", "1:1",
                                               "--hr-spp", "1000000000"), (2,), False, False, None),
    ("render: LR under 4 px", lambda f: _r("-o", str(f.root / "h3"), "--hr-size", "12x12", "--frames", "1:1"),
     (2,), False, False, None),
    # non-finite values through evaluate and upscale
    ("evaluate: Inf in the ground truth", lambda f: [
        "evaluate", "--model", "bilinear", "--data", str(f.variant("gt_inf", lambda c: _edit_exr(
            c, 2, "hr/radiance", lambda a: _set(a, (3, 4, 0), float("inf"))))), "--json", str(f.root / "n1.json")],
     (2,), True, True, lambda f, code, err: None if "000002.exr" in err else "the error names no file"),
    ("evaluate: NaN in the ground truth", lambda f: [
        "evaluate", "--model", "bicubic", "--data", str(f.variant("gt_nan", lambda c: _edit_exr(
            c, 1, "hr/radiance", lambda a: _set(a, (5, 5, 1), float("nan"))))), "--json", str(f.root / "n2.json")],
     (2,), False, True, lambda f, code, err: None if "000001.exr" in err else "the error names no file"),
    ("evaluate: NaN in an LR input (refused as validate refuses it, issue 43)", lambda f: [
        "evaluate", "--model", "bilinear", "--data", str(f.variant("lr_nan", lambda c: _edit_exr(
            c, 2, "lr/radiance", lambda a: _set(a, (3, 4, 0), float("nan"))))), "--json", str(f.root / "n3.json"),
        "--no-flip"],
     (2,), True, True, lambda f, code, err: (None if "000002.exr: frame 2 lr/radiance" in err and "[non-finite]" in err
                                             else "not validate's words naming the file")),
    ("evaluate: negative LR radiance (issue 43)", lambda f: [
        "evaluate", "--model", "bilinear", "--data", str(f.variant("lr_neg", lambda c: _edit_exr(
            c, 2, "lr/radiance", lambda a: a * 0 - 1.0))), "--json", str(f.root / "n6.json"), "--no-flip"],
     (2,), True, True, lambda f, code, err: (None if "000002.exr: frame 2 lr/radiance: radiance is negative" in err
                                             else "not validate's words naming the file")),
    ("train: negative LR radiance (issue 43)", lambda f: [
        "train", "--model", "fusesr", "--data", str(f.variant("lr_neg", None)), "-o", str(f.root / "n7"),
        "--max-steps", "1", "--set", "data.crop=8"],
     (2,), True, True, lambda f, code, err: (None if "[negative-radiance]" in err and "000002.exr" in err
                                             else "not validate's words naming the file")),
    ("upscale: NaN in an LR input", lambda f: [
        "upscale", "--model", "bilinear", "--clip", str(f.variant("lr_nan", None)), "-o", str(f.root / "n4")],
     (0,), True, True, lambda f, code, err: ("no warning" if "warning:" not in err else
                                             _sr_finite(f.root / "n4"))),
    ("upscale: Inf in an LR input", lambda f: [
        "upscale", "--model", "bicubic", "--clip", str(f.variant("lr_inf", lambda c: _edit_exr(
            c, 1, "lr/radiance", lambda a: _set(a, (2, 2, 2), float("inf"))))), "-o", str(f.root / "n5")],
     (0,), False, True, lambda f, code, err: ("no warning" if "warning:" not in err else
                                             _sr_finite(f.root / "n5"))),
    # issue 43 (reliability 3): bad input that was a traceback, an echo of None, a path printed twice, a runaway
    ("spec: scales = []", lambda f: _ds(f, "scales0", 'kind = "builtin"\nseeds = "0:0"\n', "scales = []\n"),
     (2,), True, True, _says("render.scales = []")),
    ("spec: hr_size given as a number (names the spec once)", lambda f: _ds(
        f, "hrnum", 'kind = "builtin"\nseeds = "0:0"\n', "hr_size = 5\n"), (2,), True, True,
     _names_once(lambda f: f.root / "hrnum.toml")),
    ("spec: regions = \"axb\" (echoed as written)", lambda f: (_asset_dir(f), _ds(
        f, "regions", 'kind = "scene"\npaths = ["assets"]\nregions = "axb"\n'))[1], (2,), True, True,
     _says("regions = 'axb'")),
    ("preview: --splits bogus", lambda f: ["preview", str(_preview_ds(f)), "-o", str(f.root / "p1.png"),
                                           "--splits", "bogus"], (2,), True, True,
     _says("unknown split 'bogus'", "train, val, test")),
    ("preview: --width 100000 (checked against memory)", lambda f: [
        "preview", str(_preview_ds(f)), "-o", str(f.root / "p2.png"), "--width", "100000"], (2,), True, True,
     _says("of memory")),
    ("render: --camera-path fly on a mesh of zero extent", lambda f: _r(
        str(_zero_extent_glb(f)), "-o", str(f.root / "z1"), "--camera-path", "fly", "--light", "sky", "--hr-size",
        "64x36", "--frames", "1:2", "--hr-spp", "1", "--threads", "1"), (2,), False, False, _says("zero extent")),
    ("dataset: Ray address not HOST:PORT", lambda f: _ray(f, "raybad", "not an address"), (2,), False, False,
     _says("--address not an address")),
    ("dataset: Ray Client address (ray://) with nothing there", lambda f: _ray(f, "rayclient",
                                                                               "ray://127.0.0.1:1"),
     (2,), False, False, _says("--address ray://127.0.0.1:1")),
    ("dataset: Ray address with nothing listening (a runaway before)", lambda f: _ray(
        f, "raynone", f"127.0.0.1:{_free_port()}"), (2,), False, False, _says("--address 127.0.0.1:")),
]


def huge_and_nonfinite(fx: Fixtures, tally: Tally, quick: bool, log=print) -> None:
    """Huge specs and non-finite values through evaluate and upscale (issue 26): refused in one line within
    RUNAWAY_S seconds, or accepted with a warning and finite results."""
    run_cases(HUGE_AND_NONFINITE, fx, tally, quick, log)


def run_cases(cases, fx: Fixtures, tally: Tally, quick: bool, log=print) -> None:
    """Run rows of (name, argv(fx), expected exits, quick, in-process, check) and count them."""
    for name, argv_of, expect, is_quick, inproc, check in cases:
        if quick and not is_quick:
            continue
        argv = argv_of(fx)
        t0 = time.perf_counter()
        if inproc:
            code, err, escaped = run_inproc(argv)
        else:
            try:
                proc = cli(argv, timeout=RUNAWAY_S * 3)
                code, err, escaped = proc.returncode, proc.stderr, False
            except subprocess.TimeoutExpired:
                code, err, escaped = -9, "runaway", False
        took = time.perf_counter() - t0
        tally.inputs_tried += 1
        problems = []
        if escaped or TRACEBACK in err:
            tally.tracebacks += 1
            problems.append("traceback")
        if code not in expect:
            tally.wrong_exit += 1
            problems.append(f"exit {code}, expected {expect}")
        elif took > RUNAWAY_S:
            tally.wrong_exit += 1
            problems.append(f"runaway: {took:.0f} s")
        if code == 2 and "error:" not in err:
            tally.no_error_line += 1
            problems.append("no 'error:' line")
        extra = check(fx, code, err) if check is not None and code in expect else None
        if extra:
            tally.results_differ += 1
            problems.append(extra)
        if problems:
            last = [ln for ln in err.strip().splitlines() if ln.strip()][-1:] or [""]
            tally.fail(f"{name}: {', '.join(problems)}: {last[0][:200]}")
        log(f"  {'FAIL' if problems else 'ok  '} {name}: exit {code} ({took:.1f} s)")


# ------------------------------------------------------------------ issue 56: frames with nothing, untrusted clips
def _scene_file(fx: Fixtures, name: str, data) -> Path:
    """A scene file under the fixtures: ``data`` text or bytes."""
    p = fx.root / "scenes56" / name
    p.parent.mkdir(exist_ok=True)
    p.write_bytes(data if isinstance(data, bytes) else data.encode())
    return p


def _stl(triangles: int, value: float = float("nan"), cut: int | None = None) -> bytes:
    import struct
    tri = struct.pack("<12fH", *([0.0] * 3 + [value] * 9), 0)
    data = b"\0" * 80 + struct.pack("<I", triangles) + tri * triangles
    return data[:cut] if cut else data


def _render_scene(fx: Fixtures, name: str, data) -> list[str]:
    return _r(str(_scene_file(fx, name, data)), "-o", str(fx.root / f"out56_{name}"), "--camera-path", "orbit",
              "--light", "sky", "--hr-size", "32x32", "--frames", "1:1", "--hr-spp", "1", "--lr-spp", "1",
              "--threads", "1", "--no-progress")


def _fixed_exposure(value: float):
    """A mutation: the clip as rendered at a fixed exposure of 0.5 (identity stamped), then ``exposure.value`` set
    to ``value`` in its manifest (None: the exposure nulled; 0: deleted)."""
    def mutate(c: Path):
        from gbuffer_export.clip import header_identity
        m = json.loads((c / "manifest.json").read_text())
        m["exposure"] = {"mode": "fixed", "value": 0.5}
        m["identity"] = header_identity(m)
        if value is None:
            m["exposure"] = None
        elif value == 0:
            del m["exposure"]
        else:
            m["exposure"]["value"] = value
        (c / "manifest.json").write_text(json.dumps(m))
    return mutate


def _dim(c: Path) -> None:
    for f in (1, 2, 3, 4):
        _edit_exr(c, f, "hr/radiance", lambda a: a * 1e-5)


def _consumers(variant: str, mutate, check: str, quick: bool = False) -> list:
    """Rows: train, evaluate, upscale and export-dataset on the clip variant, each refused naming the check."""
    def clip(f):
        return str(f.variant(variant, mutate))

    def clip2(f):  # NSS reads a 2x level: the scale-2 clip, so that nothing else refuses it
        return str(f.variant(f"{variant}_x2", mutate, base=f.clip2))
    says = _says("fails validation", f"[{check}]")
    return [
        (f"train: {variant}", lambda f: ["train", "--model", "fusesr", "--data", clip(f), "-o",
                                          str(f.root / f"t56_{variant}"), "--max-steps", "1", "--set",
                                          "data.crop=8"], (2,), quick, True, says),
        (f"evaluate: {variant}", lambda f: ["evaluate", "--model", "bilinear", "--data", clip(f), "--json",
                                             str(f.root / f"e56_{variant}.json"), "--no-flip"], (2,), quick, True,
         says),
        (f"upscale: {variant}", lambda f: ["upscale", "--model", "bilinear", "--clip", clip(f), "-o",
                                            str(f.root / f"u56_{variant}")], (2,), False, True, says),
        (f"export-dataset: {variant}", lambda f: ["export-dataset", clip2(f), "--format", "nss", "-o",
                                                   str(f.root / f"x56_{variant}")], (2,), False, True, says),
    ]


def _ply_missing_vertex() -> str:
    return ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")


#: Issue 56 items 2 and 3: scenes whose geometry renders nothing (refused before rendering, in one line naming the
#: file) and clips that fail validation (refused by every consumer naming the failed check).
EMPTY_AND_UNTRUSTED = [
    ("render: truncated OBJ (vertices, no faces)", lambda f: _render_scene(
        f, "truncated.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2"), (2,), True, False,
     _says("truncated.obj: ", "no faces")),
    ("render: truncated STL", lambda f: _render_scene(f, "truncated.stl", _stl(40, 1.0, cut=400)), (2,), False,
     False, _says("truncated.stl: ")),
    ("render: random-bytes STL", lambda f: _render_scene(f, "random.stl", random.Random(5).randbytes(2000)), (2,),
     False, False, _says("random.stl: ")),
    ("render: every vertex NaN (STL)", lambda f: _render_scene(f, "nan.stl", _stl(4)), (2,), False, False,
     _says("nan.stl: ")),
    ("render: PLY face naming a missing vertex", lambda f: _render_scene(f, "missing.ply", _ply_missing_vertex()),
     (2,), False, False, _says("missing.ply: ")),
    ("render: zero-extent mesh (scene camera orbit)", lambda f: _render_scene(
        f, "zero.obj", "v 2 2 2\nv 2 2 2\nv 2 2 2\nf 1 2 3\n"), (2,), False, False, _says("zero extent")),
    ("render: a 1e7 m level", lambda f: _render_scene(
        f, "huge.obj", "v 0 0 0\nv 1e7 0 0\nv 0 1e7 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n"), (2,), False, False,
     _says("huge.obj: ", "absurdly large")),
    *_consumers("exposure_x10", _fixed_exposure(5.0), "manifest-identity", quick=True),
    *_consumers("exposure_1e6", _fixed_exposure(1e6), "manifest-identity"),
    *_consumers("exposure_nulled", _fixed_exposure(None), "manifest-identity"),
    *_consumers("exposure_deleted", _fixed_exposure(0), "manifest-identity"),
    *_consumers("radiance_1e-5", _dim, "dark-frame", quick=True),
]


def _keep_times(path: Path, fn) -> None:
    st = os.stat(path)
    fn(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def cache_staleness(fx: Fixtures, tally: Tally, log=print) -> None:
    """The training cache after its clip changed under kept file times: an EXR rewritten must rebuild it; an EXR
    become a link must be refused (``train``: exit 2 naming the link)."""
    from training.cache import ClipCache
    clip = fx.variant("cache56", lambda c: None)
    cache = ClipCache(clip).ensure(["lr/radiance"])
    old = cache.read(2, "lr/radiance").copy()
    exr = _path(clip, 2, "lr/radiance")
    _keep_times(exr, lambda p: _edit_exr(clip, 2, "lr/radiance", lambda a: a * 2.0))
    fresh = ClipCache(clip).ensure(["lr/radiance"])
    tally.inputs_tried += 1
    if not fresh.rebuilt or not abs(float(fresh.read(2, "lr/radiance").mean()) - 2 * float(old.mean())) <= \
            1e-4 * abs(float(old.mean())):
        tally.results_differ += 1
        tally.fail("cache: an EXR rewritten under kept file times did not rebuild the cache")
    log(f"  {'ok  ' if fresh.rebuilt else 'FAIL'} cache: EXR rewritten under kept file times")
    outside = fx.root / "outside56.exr"
    shutil.copy2(exr, outside)
    exr.unlink()
    exr.symlink_to(outside)
    run_cases([("train: an EXR become a link after the cache was built", lambda f: [
        "train", "--model", "fusesr", "--data", str(clip), "-o", str(f.root / "t56_link"), "--max-steps", "1",
        "--set", "data.crop=8"], (2,), True, True, _says("symbolic link"))], fx, tally, False, log)


def empty_and_untrusted(fx: Fixtures, tally: Tally, quick: bool, log=print) -> None:
    """Issue 56 (part ``empty``): EMPTY_AND_UNTRUSTED and the cache's staleness."""
    run_cases(EMPTY_AND_UNTRUSTED, fx, tally, quick, log)
    cache_staleness(fx, tally, log)


# ------------------------------------------------------------------------------------------------ random inputs
def random_inputs(fx: Fixtures, tally: Tally, examples: int, log=print) -> None:
    """Part 2: random manifests, EXR files and training configurations (hypothesis, derandomized), each read by the
    code that takes it; a traceback is a failure."""
    from hypothesis import HealthCheck, settings

    cfg = settings(max_examples=examples, deadline=None, database=None, derandomize=True,
                   suppress_health_check=list(HealthCheck))
    work = fx.root / "hyp"
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(fx.clip, work, ignore=shutil.ignore_patterns(".blendsr_cache"))

    def check(label, fn):
        tally.inputs_tried += 1
        try:
            fn()
        except Exception as exc:
            tally.tracebacks += 1
            tally.fail(f"{label}: {type(exc).__name__}: {str(exc).splitlines()[0][:160] if str(exc) else ''}")

    before = tally.inputs_tried
    for family in (_random_manifests, _random_exrs, _random_configs):
        family(fx, work, cfg, check)()
    log(f"  {tally.inputs_tried - before} random inputs")


def _set_path(m: dict, path: tuple, value) -> dict:
    """``m`` with ``value`` at ``path`` (unchanged where a key on the way is not an object)."""
    d = m
    for k in path[:-1]:
        d = d[k] if isinstance(d, dict) and k in d else None
        if not isinstance(d, dict):
            return m
    d[path[-1]] = value
    return m


def _random_manifests(fx: Fixtures, work: Path, cfg, check):
    """The test over manifests with one key replaced by a random JSON value, or a top-level key dropped."""
    from hypothesis import given
    from hypothesis import strategies as st

    from gbuffer_export.validate import validate_clip
    base = json.loads((fx.clip / "manifest.json").read_text())
    scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                        st.text(max_size=8))
    json_values = st.recursive(scalars, lambda c: st.one_of(st.lists(c, max_size=4),
                                                            st.dictionaries(st.text(max_size=6), c, max_size=4)),
                               max_leaves=12)
    paths = [("scale",), ("levels",), ("levels", "hr"), ("levels", "lr", "width"), ("frames",), ("buffers",),
             ("frame_data",), ("frame_data", "2"), ("frame_data", "2", "hr"), ("frame_data", "2", "lr", "jitter"),
             ("frame_data", "2", "hr", "intrinsics"), ("schema",), ("schema_version",), ("render",), ("identity",)]
    set_path = _set_path  # the test's source as before the split: derandomize seeds hypothesis from it

    @cfg
    @given(st.sampled_from(paths), json_values, st.booleans())
    def manifests(path, value, drop):
        m = json.loads(json.dumps(base))
        if drop and path[0] in m:
            del m[path[0]]
        else:
            set_path(m, path, value)
        (work / "manifest.json").write_text(json.dumps(m))
        check(f"manifest {path}={value!r:.60}", lambda: validate_clip(work, quick=True))
    return manifests


def _random_exrs(fx: Fixtures, work: Path, cfg, check):
    """The test over buffer files with random channels, sample types and sizes, validated and cached."""
    from hypothesis import given
    from hypothesis import strategies as st

    from gbuffer_export.exr import write_exr
    from gbuffer_export.validate import validate_clip
    channel_sets = st.lists(st.sampled_from(["R", "G", "B", "A", "X", "Y", "Z", "F", "V", "rgb.R"]), min_size=1,
                            max_size=4, unique=True)

    @cfg
    @given(channel_sets, st.sampled_from(["float32", "float16", "uint32"]), st.integers(1, 20), st.integers(1, 40),
           st.sampled_from(["lr/radiance", "hr/normal", "hr/flags", "lr/depth"]))
    def exrs(chans, dtype, h, w, key):
        import numpy as np
        from gbuffer_export.clip import open_clip
        shutil.copyfile(fx.clip / "manifest.json", work / "manifest.json")
        path = Path(open_clip(work).path_of(2, key))
        rng = np.random.default_rng(h * 100 + w)
        arrs = {c: (rng.random((h, w)) * 10).astype(dtype) for c in chans}
        write_exr(path, arrs)

        def run():
            validate_clip(work, quick=True)
            from training.cache import ClipCache
            from gbuffer_export.clip import ClipError
            try:
                ClipCache(work, cache_dir=fx.root / "hyp_cache").ensure([key])
            except (ClipError, ValueError):
                pass
        check(f"EXR {key} {chans} {dtype} {w}x{h}", run)
        shutil.copyfile(fx.clip / Path(open_clip(fx.clip).path_of(2, key)).relative_to(fx.clip), path)
    return exrs


def _random_configs(fx: Fixtures, work: Path, cfg, check):
    """The test over training configurations of random sections, keys and values, some garbled."""
    from hypothesis import given
    from hypothesis import strategies as st

    from gbuffer_export.config import ConfigError
    from training.config import load_config
    sections = st.sampled_from(["data", "model", "loss", "optim", "run", "extra"])
    keys = st.sampled_from(["crop", "batch_size", "name", "width", "lr", "max_steps", "nonfinite", "betas",
                            "exposure_range", "scale", "pixel", "bogus"])
    toml_values = st.one_of(st.integers(-5, 10**4), st.floats(-1e3, 1e3), st.booleans(),
                            st.text(alphabet="abcxyz-_", max_size=8), st.lists(st.floats(-2, 2), max_size=3))

    @cfg
    @given(st.dictionaries(sections, st.dictionaries(keys, toml_values, max_size=3), max_size=3),
           st.booleans())
    def configs(doc, garble):
        lines = []
        for sec, kv in doc.items():
            lines.append(f"[{sec}]")
            for k, v in kv.items():
                lines.append(f"{k} = {_toml(v)}")
        text = "\n".join(lines) + "\n"
        if garble:
            text = text.replace("=", "", 1)
        p = fx.root / "hyp.toml"
        p.write_text(text)

        def run():
            try:
                load_config(p)
            except (ConfigError, ValueError):
                pass
        check(f"config {text[:80]!r}", run)
    return configs


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return repr(v)


# ---------------------------------------------------------------------------------------------- kill + resume
def _digest_dir(clip: Path) -> dict[str, str]:
    out = {}
    for p in sorted(clip.rglob("*")):
        if p.is_file() and ".blendsr_cache" not in p.parts and p.name != "manifest.json" and not p.name.startswith("."):
            out[str(p.relative_to(clip))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _finished_frames(clip: Path) -> dict[int, dict[str, str]]:
    """frame -> digests of its record and buffers, for frames whose record exists."""
    out = {}
    rec_dir = clip / "frames"
    if not rec_dir.is_dir():
        return out
    digests = _digest_dir(clip)
    for rec in rec_dir.glob("*.json"):
        f = int(rec.stem)
        out[f] = {k: v for k, v in digests.items() if Path(k).stem == rec.stem}
    return out


def _kill_loop(cmd_for, done, tally: Tally, kills: int, window: list, rng: random.Random,
               label: str, log=print, on_kill=None, late_first: bool = False) -> int:
    """Start ``cmd_for()`` and SIGKILL it after a random time in ``window`` (seconds) until ``kills`` kills were
    delivered; then run it to the end. Returns the number of kills delivered. A run that finishes before its kill
    time shrinks ``window`` to its own duration (the reference run may have been slower)."""
    delivered = 0
    while True:
        started = time.perf_counter()
        proc = subprocess.Popen(cmd_for(), cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)
        if delivered >= kills:
            t = None
        elif delivered == 0 and late_first:  # let the first process finish some work before its kill
            t = rng.uniform(0.8 * window[1] / 0.75, 0.98 * window[1] / 0.75)  # startup is ~80% of a run
        else:
            t = rng.uniform(*window)
        try:
            proc.wait(timeout=t)
            if t is not None and delivered == 0:  # a full run (a resumed one has less to do)
                took = time.perf_counter() - started
                window[:] = [min(window[0], 0.1 * took), min(window[1], 0.75 * took)]
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            delivered += 1
            tally.faults += 1
            if on_kill is not None:
                on_kill()
            continue
        err = proc.stderr.read() if proc.stderr else ""
        if proc.returncode != 0:
            if TRACEBACK in err:
                tally.tracebacks += 1
            tally.fail(f"{label}: rerun exited {proc.returncode}: {err.strip().splitlines()[-1:]}")
            return delivered
        if done():
            return delivered


def render_kills(root: Path, tally: Tally, kills: int, rng: random.Random, frames: int = 4, log=print) -> None:
    from gbuffer_export import open_clip
    from gbuffer_export.validate import validate_clip
    work = root / "render_kills"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    clip = work / "clip"
    t0 = time.perf_counter()
    args = render_args(frames)
    proc = cli(["render", "-o", str(clip), *args])
    t_ref = time.perf_counter() - t0
    if proc.returncode != 0:
        tally.fail(f"render reference failed: {proc.stderr[-500:]}")
        return
    ref = work / "reference"
    clip.rename(ref)
    ref_clip = open_clip(ref)
    log(f"  uninterrupted render: {t_ref:.1f} s")
    window = [0.1 * t_ref, 0.75 * t_ref]
    done_total = 0
    round_ = killed_rounds = 0
    while done_total < kills:
        round_ += 1
        if clip.exists():
            shutil.rmtree(clip)
        snapshots: dict[int, dict[str, str]] = {}
        first_process = {"frames": None}
        changed = {"n": 0}

        def on_kill():
            now = _finished_frames(clip)
            if first_process["frames"] is None:
                first_process["frames"] = set(now)
            for f, d in snapshots.items():
                if now.get(f) != d:
                    changed["n"] += 1
            snapshots.update(now)

        want = min(kills - done_total, 5)
        n = _kill_loop(lambda: [sys.executable, "-m", "gbuffer_export.cli", "render", "-o", str(clip), *args],
                       lambda: (clip / "manifest.json").is_file() and len(_finished_frames(clip)) == frames,
                       tally, want, window, rng, "render", log, on_kill, late_first=killed_rounds % 2 == 0)
        done_total += n
        if n == 0:
            if round_ > 3 * kills:
                break
            continue
        killed_rounds += 1
        final = _finished_frames(clip)
        for f, d in snapshots.items():
            if final.get(f) != d:
                changed["n"] += 1
        tally.changed_frames += changed["n"]
        rep = validate_clip(clip)
        if not rep.ok:
            tally.corrupt_clips += 1
            tally.fail(f"render round {round_}: {rep.summary_line()}")
        lost = frames - len(final)
        tally.lost_frames += max(lost, 0)
        first = first_process["frames"] or set()
        ok = _same_as_reference(open_clip(clip), ref_clip, first, tally, f"render round {round_}")
        tally.results_compared += 1
        tally.results_differ += 0 if ok else 1
        if rep.ok and lost == 0 and changed["n"] == 0:
            tally.faults_survived += n
        log(f"  render round {round_}: {n} kills, first process finished frames {sorted(first)}, "
            f"{'valid' if rep.ok else 'INVALID'}, {len(final)}/{frames} frames, {'same' if ok else 'DIFFERENT'}")


def _same_as_reference(c, ref_clip, first: set, tally: Tally, label: str) -> bool:
    """Every buffer of every frame of clip ``c`` against the uninterrupted render: the G-buffers bit for bit (normal
    and F_beta to 1e-6), the radiance in expectation (its HR frames counted bit-identical or resumed: ``first``, the
    frames the first process finished). Each difference is a failure of ``tally``; True when none."""
    ok = True
    for f in c.frames:
        for lvl in ("hr", "lr"):
            for b in c.manifest["buffers"]:
                a, r = c.read(f, f"{lvl}/{b}"), ref_clip.read(f, f"{lvl}/{b}")
                if b in ("depth", "albedo", "emission", "motion", "flags"):
                    same = a.tobytes() == r.tobytes()
                elif b in ("normal", "fbeta"):
                    same = bool(abs(a.astype("float64") - r).max() <= 1e-6)
                else:  # radiance: the same image in expectation (bit-identical is best effort, counted)
                    same = abs(float(a.mean()) - float(r.mean())) <= 0.05 * max(abs(float(r.mean())), 1e-3)
                if b == "radiance" and lvl == "hr":
                    if f in first:
                        tally.frames_bit_identical += int(a.tobytes() == r.tobytes())
                    else:
                        tally.frames_resumed += 1
                if not same:
                    ok = False
                    tally.fail(f"{label}: frame {f} {lvl}/{b} differs from the uninterrupted run"
                               f" ({'first process' if f in first else 'resumed'})")
    return ok


def _weights_digest(ck_path: Path) -> str:
    from training.checkpoint import load_checkpoint
    ck = load_checkpoint(ck_path)
    h = hashlib.sha256()
    for k, v in ck["model"].items():
        h.update(k.encode())
        h.update(v.cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def train_kills(fx: Fixtures, tally: Tally, kills: int, rng: random.Random, steps: int = 12, log=print) -> None:
    work = fx.root / "train_kills"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    sets = sum((["--set", s] for s in TRAIN_SETS), [])
    base = ["train", "--model", "fusesr", "--data", str(fx.clip), "--max-steps", str(steps), *sets]
    t0 = time.perf_counter()
    proc = cli([*base, "-o", str(work / "reference")])
    t_ref = time.perf_counter() - t0
    if proc.returncode != 0:
        tally.fail(f"train reference failed: {proc.stderr[-500:]}")
        return
    ref = _weights_digest(work / "reference" / "checkpoints" / "last.pt")
    log(f"  uninterrupted training ({steps} steps): {t_ref:.1f} s")
    window = [0.1 * t_ref, 0.75 * t_ref]
    done_total, round_ = 0, 0
    while done_total < kills:
        round_ += 1
        run = work / f"run{round_}"
        last = run / "checkpoints" / "last.pt"

        def cmd():
            if last.is_file():
                return [sys.executable, "-m", "gbuffer_export.cli", "train", "-o", str(run), "--resume"]
            return [sys.executable, "-m", "gbuffer_export.cli", *base, "-o", str(run)]

        def finished():
            s = run / "summary.json"
            return s.is_file() and json.loads(s.read_text()).get("step") == steps

        n = _kill_loop(cmd, finished, tally, min(kills - done_total, 5), window, rng, "train", log)
        done_total += n
        if n == 0:
            if round_ > 3 * kills:
                break
            continue
        same = last.is_file() and _weights_digest(last) == ref
        tally.results_compared += 1
        if not same:
            tally.results_differ += 1
            tally.fail(f"train round {round_}: final weights differ from the uninterrupted run")
        else:
            tally.faults_survived += n
        log(f"  train round {round_}: {n} kills, weights {'bit-identical' if same else 'DIFFERENT'}")


# ------------------------------------------------------------------------------------------------------- add-on
ADDON_SCRIPT = r'''
import json, os, sys
import bpy
import blender_addon
root = sys.argv[1]
evil = sys.argv[2]
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
bpy.ops.mesh.primitive_uv_sphere_add()
sc.frame_start, sc.frame_end = 1, 1
blender_addon.register()
s = sc.blendsr
s.use_scene_resolution = False
s.hr_width, s.hr_height = 64, 36
s.hr_spp, s.lr_spp, s.gbuffer_spp = 1, 1, 1
out = []
def attempt(name, op):
    try:
        res = op()
        out.append({"case": name, "result": sorted(res), "message": ""})
    except RuntimeError as exc:
        out.append({"case": name, "result": ["ERROR"], "message": str(exc)})
    except Exception as exc:
        import traceback
        out.append({"case": name, "result": ["EXCEPTION"], "message": traceback.format_exc()})
s.output_dir = os.path.join(root, "addon_out")
attempt("export: scene without a camera", bpy.ops.blendsr.export_dataset)
bpy.ops.object.camera_add(location=(0, -6, 0), rotation=(1.5708, 0, 0))
sc.camera = bpy.context.object
s.output_dir = os.path.join(root, "a_file")
attempt("export: output folder is a file", bpy.ops.blendsr.export_dataset)
s.output_dir = os.path.join(root, "addon_out2")
s.checkpoint = os.path.join(root, "missing.pt")
attempt("preview: missing checkpoint", bpy.ops.blendsr.preview_upscale)
s.checkpoint = evil
attempt("preview: malicious checkpoint", bpy.ops.blendsr.preview_upscale)
print("RESULT " + json.dumps(out), flush=True)
'''


def addon_inputs(fx: Fixtures, tally: Tally, log=print, cases: int | None = None) -> None:
    proc = subprocess.run([sys.executable, "-c", ADDON_SCRIPT, str(fx.root), str(fx.malicious())], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=600)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        tally.tracebacks += 1
        tally.fail(f"add-on script exited {proc.returncode}: {proc.stderr[-400:]}")
        return
    for r in json.loads(lines[-1][len("RESULT "):])[:cases]:
        tally.inputs_tried += 1
        bad = []
        if r["result"] != ["ERROR"]:
            bad.append(f"result {r['result']}")
            tally.wrong_exit += 1
        if TRACEBACK in r["message"] or "Traceback" in r["message"]:
            bad.append("traceback")
            tally.tracebacks += 1
        if bad:
            tally.fail(f"add-on {r['case']}: {', '.join(bad)}: {r['message'][:200]}")
        log(f"  {'FAIL' if bad else 'ok  '} add-on {r['case']}: {r['message'].strip().splitlines()[-1][:120]}")
    if (fx.root / "PWNED").exists():
        tally.tracebacks += 1
        tally.fail("the malicious checkpoint ran code in the add-on")


# ------------------------------------------------------------------------------------------- concurrent writers
def _outcome(tally: Tally, label: str, code: int, err: str, expect, escaped: bool = False, log=print) -> bool:
    """Count one case: its exit code must be in ``expect``, a refusal (2) must print 'error:', nothing may print a
    traceback. Returns whether it was clean."""
    tally.inputs_tried += 1
    problems = []
    if escaped or TRACEBACK in err:
        tally.tracebacks += 1
        problems.append("traceback")
    if code not in expect:
        tally.wrong_exit += 1
        problems.append(f"exit {code}, expected {expect}")
    if code == 2 and "error:" not in err:
        tally.no_error_line += 1
        problems.append("no 'error:' line")
    if problems:
        last = [ln for ln in err.strip().splitlines() if ln.strip()][-1:] or [""]
        tally.fail(f"{label}: {', '.join(problems)}: {last[0][:200]}")
    log(f"  {'FAIL' if problems else 'ok  '} {label}: exit {code}")
    return not problems


def _writer_header(clip: Path, **changes) -> dict:
    from gbuffer_export.clip import load_manifest
    h = {k: v for k, v in load_manifest(clip).items() if k not in ("frame_data", "identity")}
    h.update(changes)
    return h


def concurrent_writers(fx: Fixtures, tally: Tally, races: int = 0, log=print) -> None:
    """Part 5 (see module doc)."""
    from gbuffer_export.clip import ClipError, ClipWriter
    work = fx.root / "concurrent"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    clip = work / "clip"
    shutil.copytree(fx.clip, clip, ignore=shutil.ignore_patterns(".blendsr_cache"))
    h = _writer_header(clip)
    cases = [  # (label, header of the writer already running, header of the second one)
        ("same settings", h, h),
        ("other settings, nothing rendered yet", None, {**h, "render": {**h["render"], "seed": 99}}),
        ("the same shard twice", {**h, "shard": [1, 2]}, {**h, "shard": [1, 2]}),
        ("an unsharded writer beside a shard", {**h, "shard": [2, 2]}, h),
        ("a shard beside an unsharded writer", h, {**h, "shard": [1, 2]}),
        ("shards of another N", {**h, "shard": [1, 2]}, {**h, "shard": [2, 3]}),
    ]
    for label, first_h, second_h in cases:
        target = clip
        if first_h is None:  # a new folder claimed by a first writer that has not finished a frame
            target = work / f"new{len(label)}"
            first = ClipWriter(target, h)
        else:
            first = ClipWriter(target, first_h)
        try:
            try:
                ClipWriter(target, second_h).close()
                code, err = 0, ""
            except ClipError as exc:
                code, err = 2, f"blendsr: error: {exc}"
            except Exception:  # noqa: BLE001 - counted as a traceback
                code, err = 1, traceback.format_exc()
        finally:
            first.close()
        _outcome(tally, f"concurrent writer: {label}", code, err, (2,), log=log)
    with ClipWriter(clip, {**h, "shard": [1, 2]}), ClipWriter(clip, {**h, "shard": [2, 2]}):
        pass  # two shards of one N share the clip
    for r in range(races):
        render_race(work / f"race{r}", tally, random.Random(r), log=log)


def _render_proc(out: Path, *args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "render", "-o", str(out), *args], cwd=REPO,
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def render_race(work: Path, tally: Tally, rng: random.Random, frames: int = 3, log=print) -> None:
    """Two renders into one new folder (other seeds; the same command; two shards), started within 0.5 s."""
    from gbuffer_export.validate import validate_clip
    base = render_args(frames)
    i = base.index("--seed")
    variants = [("other seeds", [base[:i] + ["--seed", "0"] + base[i + 2:], base[:i] + ["--seed", "5"] + base[i + 2:]],
                 [0, 2]),
                ("the same command twice", [base, base], [0, 2]),
                ("two shards", [base + ["--shard", "1/2"], base + ["--shard", "2/2"]], [0, 0])]
    for label, argvs, expect in variants:
        out = work / label.replace(" ", "_")
        procs = []
        for argv in argvs:
            procs.append(_render_proc(out, *argv))
            time.sleep(rng.uniform(0.0, 0.5))
        results = [(p.wait(timeout=600), p.stderr.read()) for p in procs]
        codes = sorted(rc for rc, _ in results)
        tally.inputs_tried += 1
        errs = "".join(e for _, e in results)
        ok = True
        if TRACEBACK in errs:
            tally.tracebacks += 1
            ok = False
        if codes != expect:
            tally.wrong_exit += 1
            ok = False
        for rc, e in results:
            if rc == 2 and (len(e.strip().splitlines()) != 1 or str(out) not in e):
                tally.no_error_line += 1
                ok = False
        rep = validate_clip(out, quick=True) if (out / "manifest.json").is_file() else None
        if rep is None or not rep.ok or any(f.code == "mixed-clip" for f in rep.findings):
            tally.corrupt_clips += 1
            ok = False
        if not ok:
            tally.fail(f"render race, {label}: exits {codes} (expected {expect}), "
                       f"{rep.summary_line() if rep else 'no clip'}: {errs.strip()[-300:]}")
        log(f"  {'ok  ' if ok else 'FAIL'} render race, {label}: exits {codes}")


# ------------------------------------------------------------------------------------- traversal and symlinks
TRAVERSAL_PATHS = ["../outside", "ABS", "clips/../../outside", "clips/link", "clips/good/../../../outside", "", None,
                   42, "clips/good/../link"]


def _snapshot(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*"))}


def traversal_inputs(fx: Fixtures, tally: Tally, quick: bool = False, races: int = 0, log=print) -> None:
    """Part 6 (see module doc)."""
    from gbuffer_export.dataset.build import INDEX, SCHEMA
    work = fx.root / "traversal"
    if work.exists():
        shutil.rmtree(work)
    outside = work / "outside"
    shutil.copytree(fx.clip, outside, ignore=shutil.ignore_patterns(".blendsr_cache"))
    before = _snapshot(outside)

    def check_outside(label: str) -> None:
        if _snapshot(outside) != before:
            tally.escapes += 1
            tally.fail(f"{label}: the folder outside the dataset changed (written through the index)")
            shutil.rmtree(outside)
            shutil.copytree(fx.clip, outside, ignore=shutil.ignore_patterns(".blendsr_cache"))

    paths = TRAVERSAL_PATHS[:4] if quick else TRAVERSAL_PATHS
    for n, bad in enumerate(paths):
        ds = work / f"ds{n}" / "data"
        (ds / "clips").mkdir(parents=True)
        shutil.copytree(fx.clip, ds / "clips" / "good", ignore=shutil.ignore_patterns(".blendsr_cache"))
        (ds / "clips" / "link").symlink_to(outside, target_is_directory=True)
        value = str(outside) if bad == "ABS" else bad
        entries = [{"id": "evil", "path": value, "split": s, "scene_id": f"e{s}", "frames_planned": 4,
                    "licence": {"licence": "CC0-1.0"}} for s in ("train", "test")]
        (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "name": "t", "seed": 0,
                                            "splits": {}, "clips": entries}))
        for cmd, argv, expect in (
                ("validate", ["validate", str(ds), "--no-progress"], (1,)),
                ("train", ["train", "--model", "fusesr", "--data", str(ds), "-o", str(work / f"run{n}"),
                           "--max-steps", "1", *sum((["--set", x] for x in TRAIN_SETS), [])], (2,)),
                ("evaluate", ["evaluate", "--model", "bicubic", "--data", str(ds), "--json",
                              str(work / f"e{n}.json"), "--no-flip"], (2,))):
            code, err, escaped = run_inproc(argv)
            label = f"traversal: {cmd} with clip path {value!r}"
            _outcome(tally, label, code, err, expect, escaped, log)
            if code == 0:
                tally.escapes += 1
                tally.fail(f"{label}: accepted (read the clip outside the dataset)")
            check_outside(label)

    def link(rel: str, target: Path):
        def mutate(clip: Path):
            p = clip / rel
            if p.is_dir():
                shutil.copytree(p, target)
                shutil.rmtree(p)
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(p, target)
                p.unlink()
            p.symlink_to(target, target_is_directory=target.is_dir())
        return mutate

    links = [("a buffer", "hr/radiance/000002.exr"), ("the manifest", "manifest.json"), ("frames/", "frames"),
             ("a level folder", "lr")]
    for label, rel in links[:2] if quick else links:
        target = work / "link_targets" / label.replace(" ", "_").replace("/", "")
        clip = fx.variant(f"link_{label.replace(' ', '_').replace('/', '')}", link(rel, target))
        for cmd, argv, expect in (("validate", ["validate", str(clip), "--no-progress"], (1,)),
                                  ("train", ["train", "--model", "fusesr", "--data", str(clip), "-o",
                                             str(work / f"runl{len(label)}"), "--max-steps", "1",
                                             *sum((["--set", x] for x in TRAIN_SETS), [])], (2,))):
            code, err, escaped = run_inproc(argv)
            _outcome(tally, f"symlink: {cmd} of a clip with {label} as a link", code, err, expect, escaped, log)
            if code == 0:
                tally.escapes += 1
                tally.fail(f"symlink: {cmd} read {label} through a link")
    # the training cache folder itself a link out of the clip
    cache_target = work / "cache_target"
    cache_target.mkdir()

    def cache_link(clip: Path):
        (clip / ".blendsr_cache").symlink_to(cache_target, target_is_directory=True)
    clip = fx.variant("cache_link", cache_link)
    code, err, escaped = run_inproc(["train", "--model", "fusesr", "--data", str(clip), "-o", str(work / "runc"),
                                     "--max-steps", "1", *sum((["--set", x] for x in TRAIN_SETS), [])])
    _outcome(tally, "symlink: train with .blendsr_cache a link out of the clip", code, err, (2,), escaped, log)
    if any(cache_target.iterdir()):
        tally.escapes += 1
        tally.fail("symlink: the training cache was written through a link out of the clip")
    if races:
        resume_through_link(work, tally, log)


def resume_through_link(work: Path, tally: Tally, log=print) -> None:
    """A resumed render whose hr/radiance folder is a link out of the clip: refused, nothing written outside."""
    clip = work / "render_link"
    args = render_args(2)
    proc = cli(["render", "-o", str(clip), *args])
    if proc.returncode != 0:
        tally.fail(f"render for the link case failed: {proc.stderr[-300:]}")
        return
    outside = work / "render_link_outside"
    shutil.copytree(clip / "hr" / "radiance", outside)
    shutil.rmtree(clip / "hr" / "radiance")
    (clip / "hr" / "radiance").symlink_to(outside, target_is_directory=True)
    (clip / "frames" / "000002.json").unlink()
    before = _snapshot(outside)
    proc = cli(["render", "-o", str(clip), *args])
    _outcome(tally, "symlink: resumed render whose hr/radiance is a link", proc.returncode, proc.stderr, (2,), log=log)
    if _snapshot(outside) != before:
        tally.escapes += 1
        tally.fail("symlink: a resumed render wrote through a link out of the clip")


# ------------------------------------------------------------------------------------------ signals during render
def signal_render(root: Path, tally: Tally, signals: int, rng: random.Random, frames: int = 4, log=print) -> None:
    """Part 7 (see module doc)."""
    from gbuffer_export.validate import validate_clip
    work = root / "signals"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    args = render_args(frames)
    for r in range(signals):
        clip = work / f"clip{r}"
        proc = _render_proc(clip, *args)
        t0 = time.perf_counter()
        if r % 2 == 0:  # after the first frame, at a random moment of a later frame's passes
            while not list((clip / "frames").glob("*.json")) and proc.poll() is None and \
                    time.perf_counter() - t0 < 300:
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 0.5))
        else:  # during startup: loading bpy, building the scene, or the first frame
            time.sleep(rng.uniform(0.8, 4.0))  # (before 0.8 s: Python itself starts, before blendsr runs)
        first = time.perf_counter() - t0
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        try:
            rc = proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            rc = None
        err = proc.stderr.read()
        tally.faults += 1
        ok = True
        if rc not in (130, 0) or TRACEBACK in err:
            ok = False
            tally.tracebacks += int(TRACEBACK in err)
            tally.fail(f"signals round {r}: SIGINT gave exit {rc}: {err.strip()[-300:]}")
        if list(clip.glob(".render-*")):
            ok = False
            tally.fail(f"signals round {r}: a temporary folder stayed behind")
        if (clip / "manifest.json").is_file():
            rep = validate_clip(clip, quick=True)
            extra = {f.code for f in rep.findings} - {"missing-frame", "no-frames"}
            if extra:
                ok = False
                tally.corrupt_clips += 1
                tally.fail(f"signals round {r}: the interrupted clip has {sorted(extra)}")
        done = cli(["render", "-o", str(clip), *args])
        rep = validate_clip(clip, quick=True) if done.returncode == 0 else None
        if rep is None or not rep.ok:
            ok = False
            tally.corrupt_clips += 1
            tally.fail(f"signals round {r}: the rerun did not finish a valid clip: {done.stderr.strip()[-300:]}")
        tally.faults_survived += int(ok)
        log(f"  {'ok  ' if ok else 'FAIL'} signals round {r}: SIGINT at {first:.1f} s -> exit {rc}, rerun "
            f"{'valid' if rep is not None and rep.ok else 'INVALID'}")


#: Ctrl-C must stop ``blendsr dataset`` within this many seconds (issue 43).
DATASET_STOP_S = 10.0

DATASET_SIGNAL_SPEC = """[dataset]
name = "ctrlc"
seed = 1
[render]
frames = 2
hr_size = "64x32"
hr_spp = 1
lr_spp = 1
gbuffer_spp = 1
hr_denoise = false
[[source]]
name = "builtin"
kind = "builtin"
seeds = "0:2"
cameras = ["scene"]
"""


def _children_of(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (psutil; [] once it has exited)."""
    import psutil
    try:
        return [c.pid for c in psutil.Process(pid).children()]
    except psutil.NoSuchProcess:
        return []


def signal_dataset(root: Path, tally: Tally, rng: random.Random, rounds: int = 2, log=print) -> None:
    """Part 10 (issue 43): SIGINT to the process group (a terminal's Ctrl-C; even rounds) or to the coordinator
    alone (odd rounds) at a random moment after a dataset's first frame: exit 130 within ``DATASET_STOP_S``, no
    clip process left, no clip started after it; the rerun finishes every clip and the dataset validates."""
    work = root / "dataset_signals"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    spec = work / "spec.toml"
    spec.write_text(DATASET_SIGNAL_SPEC)
    for r in range(rounds):
        out = work / f"ds{r}"
        proc = subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "dataset", str(spec), "-o", str(out),
                                 "--threads", "1", "--no-progress"], cwd=REPO, env=ENV, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True, start_new_session=True)
        t0 = time.perf_counter()
        while not list(out.glob("clips/*/frames/*.json")) and proc.poll() is None and time.perf_counter() - t0 < 300:
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 0.5))
        children = _children_of(proc.pid)
        started = {p.name for p in (out / "clips").iterdir()} if (out / "clips").is_dir() else set()
        t1 = time.perf_counter()
        if proc.poll() is None:
            (os.killpg if r % 2 == 0 else os.kill)(proc.pid, signal.SIGINT)
        try:
            rc = proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            rc = None
        took = time.perf_counter() - t1
        err = proc.stderr.read()
        tally.faults += 1
        problems = []
        if rc != 130 or TRACEBACK in err:
            tally.tracebacks += int(TRACEBACK in err)
            problems.append(f"exit {rc}: {err.strip()[-200:]}")
        if took > DATASET_STOP_S:
            problems.append(f"stopped after {took:.1f} s")
        if any(Path(f"/proc/{c}").exists() and "Z" not in Path(f"/proc/{c}/stat").read_text().rsplit(")", 1)[1][:3]
               for c in children):
            problems.append("a clip process outlived the coordinator")
        later = {p.name for p in (out / "clips").iterdir()} - started if (out / "clips").is_dir() else set()
        if later:
            problems.append(f"clips started after Ctrl-C: {sorted(later)}")
        done = cli(["dataset", str(spec), "-o", str(out), "--threads", "1", "--no-progress"])
        valid = cli(["validate", str(out), "--quick", "--no-progress"]) if done.returncode == 0 else None
        if valid is None or valid.returncode != 0:
            tally.corrupt_clips += 1
            problems.append(f"the rerun did not finish a valid dataset: {(done.stderr or '').strip()[-200:]}")
        for pr in problems:
            tally.fail(f"dataset signals round {r} ({'group' if r % 2 == 0 else 'coordinator'}): {pr}")
        tally.faults_survived += int(not problems)
        log(f"  {'FAIL' if problems else 'ok  '} dataset signals round {r}: SIGINT to the "
            f"{'group' if r % 2 == 0 else 'coordinator'} -> exit {rc} in {took:.1f} s")


# -------------------------------------------------------------------------------------------- full filesystem
def full_filesystem(fx: Fixtures, tally: Tally, log=print) -> None:
    """Part 8 (see module doc)."""
    import errno
    from unittest import mock

    from gbuffer_export.clip import ClipError
    from training.cache import ClipCache
    work = fx.root / "fullfs"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)

    def no_space(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")
    with mock.patch.object(os, "posix_fallocate", no_space):
        try:
            ClipCache(fx.clip, cache_dir=work / "sim").ensure(["lr/radiance", "hr/radiance"])
            code, err = 0, ""
        except ClipError as exc:
            code, err = 2, f"blendsr: error: {exc}"
        except Exception:  # noqa: BLE001
            code, err = 1, traceback.format_exc()
    _outcome(tally, "full filesystem: cache with a simulated ENOSPC", code, err, (2,), log=log)
    if [p for p in (work / "sim").rglob("*") if ".tmp" in p.name]:
        tally.fail("full filesystem: a temporary cache file stayed behind (simulated)")
    mnt = work / "mnt"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True).returncode:
        log("  (no tmpfs: mounting needs root; the real full-filesystem case is skipped)")
        return
    try:
        from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
        big = make_synthetic_clip(work / "big", frames=range(1, 5), hr_size=(256, 144), scale=4, look=SyntheticLook(hr_supersample=1))
        proc = cli(["train", "--model", "fusesr", "--data", str(big), "-o", str(work / "run"), "--max-steps", "1",
                    *sum((["--set", x] for x in TRAIN_SETS if not x.startswith("data.crop")), []),
                    "--set", f'data.cache_dir="{mnt}"'])
        _outcome(tally, "full filesystem: training cache on a 1 MB tmpfs", proc.returncode, proc.stderr, (2,),
                 log=log)
        if [p for p in mnt.rglob("*") if ".tmp" in p.name]:
            tally.fail("full filesystem: a temporary cache file stayed behind on the tmpfs")
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)
    spec = work / "spec.toml"
    spec.write_text(DATASET_SIGNAL_SPEC)
    for name, argv, expect in (
            ("render", ["render", "-o", str(mnt / "clip"), *render_args(4)], (2,)),
            ("dataset", ["dataset", str(spec), "-o", str(mnt / "ds"), "--threads", "1", "--no-progress"], (1, 2))):
        if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)],
                          capture_output=True).returncode:
            return
        try:
            code, err = _filled_during(argv, mnt)
            label = f"full filesystem: the disk fills during {name} (issue 43)"
            if _outcome(tally, label, code, err, expect, log=log) and \
                    "no space left on device" in err and f"{mnt}/" not in err:
                tally.fail(f"{label}: the error names no file: {err.strip()[-200:]}")
            left = [str(p) for p in mnt.rglob("*") if ".tmp" in p.name]
            if left:
                tally.fail(f"{label}: temporary files stayed behind: {left[:3]}")
        finally:
            subprocess.run(["umount", str(mnt)], capture_output=True)


def _filled_during(argv: list[str], mnt: Path) -> tuple[int, str]:
    """Run ``blendsr ARGV`` and fill the file system ``mnt`` once its first frame is written: (exit, stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", *argv], cwd=REPO, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.perf_counter()
    while not list(mnt.glob("**/frames/*.json")) and proc.poll() is None and time.perf_counter() - t0 < 300:
        time.sleep(0.02)
    with contextlib.suppress(OSError):  # closing a file whose last write failed raises ENOSPC again
        with open(mnt / "filler", "wb", buffering=0) as f:
            while True:
                f.write(b"\0" * 65536)
    out, err = proc.communicate(timeout=600)
    (mnt / "filler").unlink()
    return proc.returncode, out + err



# ------------------------------------------------------------------------------- scene files in a sandbox (issue 56)
#: Render flags of the sandbox cases: the smallest render that imports the scene.
SANDBOX_RENDER = ["--hr-size", "32x32", "--frames", "1:1", "--hr-spp", "1", "--lr-spp", "1", "--threads", "1",
                  "--no-progress", "--camera-path", "orbit"]
SANDBOX_BPY = r"""
import sys, bpy
out, kind = sys.argv[-2], sys.argv[-1]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.mesh.primitive_cube_add()
if kind == "fbx":
    bpy.ops.object.light_add(type="POINT", location=(2, 2, 3))
    bpy.ops.object.camera_add(location=(6, -6, 4))
    bpy.ops.export_scene.fbx(filepath=out)
elif kind == "abc":
    bpy.context.scene.frame_end = 3
    bpy.ops.wm.alembic_export(filepath=out, as_background_job=False, start=1, end=3)
elif kind == "lib":
    bpy.ops.wm.save_as_mainfile(filepath=out)
elif kind == "linker":
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with bpy.data.libraries.load(sys.argv[-3], link=True) as (src, dst):
        dst.objects = list(src.objects)
    for ob in dst.objects:
        bpy.context.scene.collection.objects.link(ob)
    bpy.ops.wm.save_as_mainfile(filepath=out, relative_remap=False)
"""


def _bpy_fixture(out: Path, kind: str, *extra: str) -> Path:
    if not out.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-c", SANDBOX_BPY, *extra, str(out), kind], check=True, env=ENV,
                       capture_output=True, timeout=300)
    return out


def _gltf(folder: Path, name: str, buffer_uri: str | None = None, image_uri: str | None = None,
          count: int = 3) -> Path:
    """A one-triangle glTF whose buffer is ``buffer_uri`` (default: an inline data: URI) and whose material's base
    colour texture is ``image_uri`` (none by default); ``count``: its position accessor's count."""
    import base64
    folder.mkdir(parents=True, exist_ok=True)
    data = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack("<6f", 0, 0, 1, 0, 0, 1)
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "buffers": [{"byteLength": len(data), "uri": buffer_uri or
                        "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                           {"buffer": 0, "byteOffset": 36, "byteLength": 24}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": count, "type": "VEC3",
                          "min": [0, 0, 0], "max": [1, 1, 0]},
                         {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}}]}]}
    if image_uri:
        doc.update(images=[{"uri": image_uri}], textures=[{"source": 0}],
                   materials=[{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}])
        doc["meshes"][0]["primitives"][0]["material"] = 0
    p = folder / name
    p.write_text(json.dumps(doc))
    return p


def _png(path: Path) -> Path:
    import numpy as np
    from PIL import Image
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((4, 4, 3), (250, 10, 10), np.uint8)).save(path)
    return path


def _obj(folder: Path, mtl_line: str, name: str = "level.obj") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "level.mtl").write_text(f"newmtl m\nKd 0.8 0.8 0.8\n{mtl_line}\n")
    p = folder / name
    p.write_text("mtllib level.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3\n")
    return p


def _link(link: Path, target: Path) -> Path:
    link.parent.mkdir(parents=True, exist_ok=True)
    if not link.is_symlink():
        link.symlink_to(target)
    return link


def _ply_4e9(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / "huge.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty "
                  b"float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                  + struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0))
    return p


def _abc_broken(folder: Path, how: str) -> Path:
    good = _bpy_fixture(folder / "good.abc", "abc")
    p = folder / f"{how}.abc"
    data = good.read_bytes()
    p.write_bytes(data[:len(data) // 2] if how == "truncated" else data[:64] + random.Random(5).randbytes(8192))
    return p


def _blend_linking_outside(work: Path) -> Path:
    lib = _bpy_fixture(work / "elsewhere" / "lib.blend", "lib")
    return _bpy_fixture(work / "level_blend" / "linker.blend", "linker", str(lib))


def _fifo(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "pipe.bin").exists():
        os.mkfifo(folder / "pipe.bin")
    return _gltf(folder, "fifo.gltf", "pipe.bin")


def _render(scene: Path, out: Path, *extra: str) -> list[str]:
    return ["render", str(scene), "-o", str(out), *SANDBOX_RENDER, *extra]


def _lists_outside(path_of):
    """A check: the clip's manifest lists the file read from the allowed folder."""
    def check(w, code, err):
        m = json.loads((w / "o_allowed" / "manifest.json").read_text())
        return None if str(path_of(w).resolve()) in m["scene"].get("read_outside", []) and \
            m["scene"].get("allow_read") else f"the manifest lists no outside file: {m['scene']}"
    return check


def _no_clip(name):
    return lambda w, code, err: (f"a clip was written to {name}" if (w / name / "manifest.json").exists() or
                                 list((w / name).glob("frames/*.json")) else None)


#: name, argv(work), expected exit codes, quick, words the message must hold (None: a successful render), env.
SANDBOX_CASES = [
    ("glTF buffer URI ../../../../etc/passwd", lambda w: _render(_gltf(w / "g1", "s.gltf", "../../../../etc/passwd"),
                                                                  w / "o1"), (2,), True, ("s.gltf", "buffers[0]")),
    ("glTF buffer URI /etc/passwd", lambda w: _render(_gltf(w / "g2", "s.gltf", "/etc/passwd"), w / "o2"), (2,),
     False, ("s.gltf", "/etc/passwd")),
    ("glTF buffer URI /dev/zero", lambda w: _render(_gltf(w / "g3", "s.gltf", "/dev/zero"), w / "o3"), (2,), True,
     ("s.gltf", "/dev/zero")),
    ("glTF buffer through a link to /dev/zero", lambda w: (_link(w / "g4" / "zero.bin", Path("/dev/zero")), _render(
        _gltf(w / "g4", "s.gltf", "zero.bin"), w / "o4"))[1], (2,), False, ("s.gltf", "zero.bin")),
    ("glTF buffer that is a FIFO in the folder", lambda w: _render(_fifo(w / "g5"), w / "o5"), (2,), False,
     ("fifo.gltf", "not a regular file")),
    ("glTF image URI outside the folder", lambda w: (_png(w / "theirs" / "red.png"), _render(
        _gltf(w / "g6", "s.gltf", image_uri="../theirs/red.png"), w / "o6"))[1], (2,), True,
     ("s.gltf", "images[0]", "--allow-read")),
    ("glTF image URI outside, folder allowed (listed in the manifest)", lambda w: (_png(w / "theirs" / "red.png"),
     _render(_gltf(w / "g7", "s.gltf", image_uri="../theirs/red.png"), w / "o_allowed", "--allow-read",
             str(w / "theirs")))[1], (0,), False, None),
    ("OBJ map_Kd ../../../etc/shadow", lambda w: _render(_obj(w / "ob1", "map_Kd ../../../../../../etc/shadow"),
                                                          w / "o8"), (2,), True, ("level.obj", "map_Kd")),
    ("OBJ map_Kd an absolute path", lambda w: (_png(w / "theirs" / "red.png"), _render(
        _obj(w / "ob2", f"map_Kd -s 1 1 1 {w / 'theirs' / 'red.png'}"), w / "o9"))[1], (2,), False,
     ("level.obj", "red.png")),
    ("OBJ map_Kd through a link outside", lambda w: (_link(w / "ob3" / "tex.png", _png(w / "theirs" / "red.png")),
                                                      _render(_obj(w / "ob3", "map_Kd tex.png"), w / "o10"))[1],
     (2,), False, ("level.obj", "a link to")),
    (".blend linking a library outside its folder", lambda w: _render(_blend_linking_outside(w), w / "o11"), (2,),
     False, ("linker.blend", "library")),
    ("glTF accessor count 10^9", lambda w: _render(_gltf(w / "g8", "s.gltf", count=10**9), w / "o12"), (2,), True,
     ("s.gltf", "accessors[0]", "1000000000")),
    ("a folder named s.glb", lambda w: ((w / "g9" / "s.glb").mkdir(parents=True, exist_ok=True),
                                        _render(w / "g9" / "s.glb", w / "o13"))[1], (2,), True,
     ("s.glb", "is a folder")),
    ("PLY declaring 4e9 vertices", lambda w: _render(_ply_4e9(w / "p1"), w / "o14"), (2,), False,
     ("huge.ply", "PLY")),
    ("truncated Alembic", lambda w: _render(_abc_broken(w / "a1", "truncated"), w / "o15"), (2,), False,
     ("truncated.abc", "Alembic")),
    ("Alembic with garbage after a valid header", lambda w: _render(_abc_broken(w / "a2", "garbage"), w / "o16"),
     (2,), False, ("garbage.abc", "Alembic")),
    ("FBX with a lamp (Blender 5.0's own export) imports", lambda w: _render(
        _bpy_fixture(w / "f1" / "lamp.fbx", "fbx"), w / "o17"), (0,), True, None),
    ("import past its time limit", lambda w: _render(_gltf(w / "g10", "s.gltf"), w / "o18"), (2,), False,
     ("s.gltf", "time limit"), {"BLENDSR_IMPORT_TIME_S": "0.01"}),
]


def sandbox_imports(work: Path, tally: Tally, quick: bool, log=print, names=None, sigint: bool = True) -> None:
    """Issue 56, item 1: every importer reads only the scene's folder (and allowed ones), a crash or limit in it is
    one line (exit 2), Ctrl-C during the import stops with exit 130 and no clip. ``names``: only the cases named so
    (the fast suite's representatives); ``sigint=False`` leaves out the Ctrl-C case."""
    work.mkdir(parents=True, exist_ok=True)
    for case in SANDBOX_CASES:
        name, argv_of, expect, is_quick, words = case[:5]
        if (quick and not is_quick) or (names is not None and name not in names):
            continue
        env = dict(ENV, **(case[5] if len(case) > 5 else {}))
        t0 = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", *argv_of(work)], cwd=REPO, env=env,
                                  capture_output=True, text=True, timeout=RUNAWAY_S * 5)
            code, err = proc.returncode, proc.stderr
        except subprocess.TimeoutExpired:
            code, err = -9, "runaway"
        took = time.perf_counter() - t0
        tally.inputs_tried += 1
        problems = []
        if TRACEBACK in err:
            tally.tracebacks += 1
            problems.append("traceback")
        if code not in expect:
            tally.wrong_exit += 1
            problems.append(f"exit {code}, expected {expect}")
        if code == 2:
            lines = [ln for ln in err.strip().splitlines() if "error:" in ln]
            if not lines:
                tally.no_error_line += 1
                problems.append("no 'error:' line")
            elif words and any(w not in lines[-1] for w in words):
                tally.results_differ += 1
                problems.append(f"the line does not say {[w for w in words if w not in lines[-1]]}")
        if code in expect and expect == (0,) and "o_allowed" in " ".join(argv_of(work)):
            extra = _lists_outside(lambda w: w / "theirs" / "red.png")(work, code, err)
            if extra:
                tally.escapes += 1
                problems.append(extra)
        if problems:
            last = [ln for ln in err.strip().splitlines() if ln.strip()][-1:] or [""]
            tally.fail(f"sandbox: {name}: {', '.join(problems)}: {last[0][:240]}")
        log(f"  {'FAIL' if problems else 'ok  '} {name}: exit {code} ({took:.1f} s)")
    if sigint:
        sigint_during_import(work, tally, log)


#: Ctrl-C during an import must stop the render within this many seconds.
IMPORT_STOP_S = 10.0


def _big_obj(folder: Path) -> Path:
    """An OBJ of 300k triangles (a few seconds to import)."""
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / "big.obj"
    if not p.is_file():
        n = 400
        rows = [f"v {i % n} {i // n} {((i * 7919) % 13) * 0.01}" for i in range(n * n)]
        faces = [f"f {r * n + c + 1} {r * n + c + 2} {(r + 1) * n + c + 1}" for r in range(n - 1) for c in
                 range(n - 1)]
        p.write_text("\n".join(rows + faces) + "\n")
    return p


def sigint_during_import(work: Path, tally: Tally, log=print) -> None:
    """SIGINT to the render's process group while its import child runs: exit 130 within IMPORT_STOP_S, no
    traceback, no clip, no import child left."""
    import psutil
    scene, out = _big_obj(work / "big"), work / "o_sigint"
    proc = subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", *_render(scene, out)], cwd=REPO, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    t0, child = time.perf_counter(), None
    while child is None and proc.poll() is None and time.perf_counter() - t0 < 300:
        kids = [c for c in psutil.Process(proc.pid).children() if "import_job" in " ".join(c.cmdline())]
        child = kids[0] if kids else None
        time.sleep(0.05)
    time.sleep(0.2)
    sent = time.perf_counter()
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
    try:
        rc = proc.wait(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        rc = proc.wait()
    took = time.perf_counter() - sent
    err = proc.stderr.read()
    tally.inputs_tried += 1
    tally.faults += 1
    problems = []
    if child is None:
        problems.append("no import child was seen")
    if rc != 130 or TRACEBACK in err:
        tally.tracebacks += int(TRACEBACK in err)
        problems.append(f"exit {rc}, expected 130")
    if took > IMPORT_STOP_S:
        problems.append(f"stopped {took:.1f} s after the signal")
    if (out / "manifest.json").exists() or list(out.glob("frames/*.json")):
        tally.corrupt_clips += 1
        problems.append("a clip was written")
    if child is not None and child.is_running() and child.status() != psutil.STATUS_ZOMBIE:
        problems.append("the import child outlived the render")
        child.kill()
    if problems:
        tally.fail(f"sandbox: Ctrl-C during the import: {', '.join(problems)}: {err.strip()[-240:]}")
    else:
        tally.faults_survived += 1
    log(f"  {'FAIL' if problems else 'ok  '} Ctrl-C during the import: exit {rc} {took:.1f} s after the signal")

# ------------------------------------------------------------------------------------------------------ exports
def _append_race(src: dict, fmt: str, work: Path) -> tuple[list[int], str, dict]:
    """Export ``src['base']`` as ``fmt``, then two ``--append`` (``a``, ``b``) started while the campaign holds the
    export's lock, let go once both wait: (exit codes, stderr of both, {sequence or scene: frames})."""
    from gbuffer_export.locks import FolderLock
    out = work / "out"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    cli(["export-dataset", str(src["base"]), "--format", fmt, "-o", str(out)])
    held = FolderLock(out, "the campaign holds it")
    logs = [work / "a.log", work / "b.log"]
    try:
        procs = []
        for k, log_path in zip(("a", "b"), logs):
            with open(log_path, "w") as f:
                procs.append(subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "export-dataset",
                                               str(src[k]), "--format", fmt, "-o", str(out), "--append"],
                                              cwd=REPO, env=ENV, stdout=f, stderr=f))
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 120 and any(p.poll() is None for p in procs):
            if all("waiting for it" in g.read_text() for g in logs):
                break
            time.sleep(0.1)
    finally:
        held.close()
    codes = [p.wait(timeout=600) for p in procs]
    if fmt == "rdg":
        got = {ln.split()[0]: int(ln.split()[1]) for ln in (out / "meta_info_train.txt").read_text().splitlines()}
    else:
        got = {j.stem: len(json.loads(j.read_text())["Frames"]) for j in out.glob("*.json")}
        for seq, n in got.items():  # a sequence mixing two appends holds more files than its JSON has frames
            if len(list((out / "ground_truth" / seq).glob("*.exr"))) != n:
                got[seq] = -1
    return codes, "".join(g.read_text() for g in logs), got


def export_cases(fx: Fixtures, tally: Tally, quick: bool = False, log=print) -> None:
    """Part 12 (issue 56 item 4, issue 57 item 4): two ``--append`` at once for every format (NFRU on 1920x1080
    clips unless ``quick``) lose no sequence; the NFRU refusal of a missing 2x level names NFRU; an NFRU export
    its reader cannot load (not 1920x1080) is refused before anything is written; the NSS round trip validates."""
    from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
    work = fx.root / "exports"
    small = {k: fx.root / f"exp_{k}" for k in ("base", "a", "b")}
    for k, n in zip(small, (1, 3, 2)):
        if not small[k].exists():
            make_synthetic_clip(small[k], frames=range(1, n + 1), hr_size=(32, 16), scales=(2, 4))
    sets = {"nss": small, "rdg": small}
    if not quick:
        hd = {k: fx.root / f"exp_hd_{k}" for k in ("base", "a", "b")}
        for k in hd:
            if not hd[k].exists():
                make_synthetic_clip(hd[k], frames=(1,), hr_size=(1920, 1080), scales=(2,),
                                    buffers=("radiance", "depth", "motion"), look=SyntheticLook(hr_supersample=1))
        sets["nfru"] = hd
    for fmt, src in sets.items():
        label = f"exports: two --append at once ({fmt})"
        codes, err, got = _append_race(src, fmt, work / fmt)
        tally.inputs_tried += 1
        if TRACEBACK in err:
            tally.tracebacks += 1
        want = 3 if fmt != "rdg" else {src[k].name: n for k, n in (("base", 1), ("a", 3), ("b", 2))}
        if codes != [0, 0] or (len(got) != want if fmt != "rdg" else got != want) or -1 in got.values():
            tally.lost_frames += 1
            tally.fail(f"{label}: exits {codes}, the export lists {got}")
        log(f"  {'ok  ' if codes == [0, 0] else 'FAIL'} {label}: {len(got)} sequences or scenes")
    proc = cli(["export-dataset", str(fx.clip), "--format", "nfru", "-o", str(work / "nfru4")])
    if _outcome(tally, "exports: NFRU without a 2x level", proc.returncode, proc.stderr, (2,), log=log) and \
            ("NSS" in proc.stderr or "NFRU needs a 2x level" not in proc.stderr):
        tally.fail(f"exports: the NFRU refusal names another format: {proc.stderr.strip()[-200:]}")
    proc = cli(["export-dataset", str(fx.clip2), "--format", "nfru", "-o", str(work / "nfru_small")])
    if _outcome(tally, "exports: NFRU at 64x36 (its reader loads 1920x1080)", proc.returncode, proc.stderr, (2,),
                log=log) and ("1920x1080" not in proc.stderr or (work / "nfru_small").exists()
                              or list(work.glob(".nfru_small.*"))):
        tally.fail(f"exports: the NFRU size refusal wrote something or named no fix: {proc.stderr.strip()[-200:]}")
    proc = cli(["export-dataset", str(fx.clip2), "--format", "nss", "-o", str(work / "nss_rt")])
    back = work / "nss_rt_clip"
    if back.exists():
        shutil.rmtree(back)
    if proc.returncode == 0:
        proc = cli(["import-nss", str(work / "nss_rt"), "-o", str(back)])
    if proc.returncode == 0:
        proc = cli(["validate", str(back)])
    _outcome(tally, "exports: the NSS round trip validates", proc.returncode, proc.stderr, (0,), log=log)


# --------------------------------------------------------------------------------------------------------- main
def campaign(out: Path, *, kills: int = 10, examples: int = 40, quick: bool = False, seed: int = 0,
             parts=("bad", "random", "render", "train", "addon", "concurrent", "traversal", "signals", "fullfs",
                    "huge", "dsignals", "sandbox", "exports", "empty"),
             signals: int = 4, races: int = 1, log=print) -> Tally:
    rng = random.Random(seed)
    tally = Tally()
    tally.log = log
    fx = Fixtures(out / "fixtures")
    if "bad" in parts:
        log("bad inputs:")
        bad_inputs(fx, tally, quick, log)
    if "huge" in parts:
        log("huge specs, non-finite values through evaluate and upscale:")
        huge_and_nonfinite(fx, tally, quick, log)
    if "empty" in parts:
        log("frames with nothing in them, clips that fail validation, cache staleness (issue 56):")
        empty_and_untrusted(fx, tally, quick, log)
    if "random" in parts:
        log("random inputs (hypothesis):")
        random_inputs(fx, tally, examples, log)
    if "render" in parts and kills:
        log("render: SIGKILL + resume:")
        render_kills(out, tally, kills, rng, log=log)
    if "train" in parts and kills:
        log("train: SIGKILL + resume:")
        train_kills(fx, tally, kills, rng, log=log)
    if "addon" in parts:
        log("add-on operators:")
        addon_inputs(fx, tally, log)
    if "concurrent" in parts:
        log("concurrent writers:")
        concurrent_writers(fx, tally, races=0 if quick else races, log=log)
    if "traversal" in parts:
        log("traversal and symlinks:")
        traversal_inputs(fx, tally, quick=quick, races=0 if quick else races, log=log)
    if "signals" in parts and signals:
        log("signals during render:")
        signal_render(out, tally, signals, rng, log=log)
    if "fullfs" in parts:
        log("full filesystem:")
        full_filesystem(fx, tally, log=log)
    if "dsignals" in parts and signals:
        log("signals during a dataset:")
        signal_dataset(out, tally, rng, rounds=2, log=log)
    if "sandbox" in parts:
        log("scene files in a sandbox (issue 56):")
        sandbox_imports(out / "sandbox", tally, quick, log)
    if "exports" in parts:
        log("exports (appends at once, consumer limits, the NSS round trip):")
        export_cases(fx, tally, quick=quick, log=log)
    return tally


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("-o", "--output", type=Path, required=True, help="work folder (created; reused fixtures)")
    p.add_argument("--kills", type=int, default=10, help="SIGKILLs per command (render, train)")
    p.add_argument("--examples", type=int, default=40, help="hypothesis examples per random-input family")
    p.add_argument("--quick", action="store_true", help="the make-test subset of the bad inputs")
    p.add_argument("--parts", default="bad,random,render,train,addon,concurrent,traversal,signals,fullfs,huge,"
                                      "dsignals,sandbox,exports,empty",
                   help="comma-separated parts to run")
    p.add_argument("--signals", type=int, default=4, help="SIGINT rounds of part 7 (renders)")
    p.add_argument("--races", type=int, default=1, help="rounds of render races (part 5) and the resumed render "
                                                        "through a link (part 6); 0: in-process cases only")
    p.add_argument("--seed", type=int, default=0, help="seed of the kill times")
    p.add_argument("--json", type=Path, help="write the counts here")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    tally = campaign(args.output, kills=args.kills, examples=args.examples, quick=args.quick, seed=args.seed,
                     parts=tuple(args.parts.split(",")), signals=args.signals, races=args.races)
    counts = {k: v for k, v in asdict(tally).items() if k != "failures"}
    counts["seconds"] = round(time.perf_counter() - t0, 1)
    print("counts: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    for f in tally.failures:
        print(f"FAILURE: {f}")
    if args.json:
        args.json.write_text(json.dumps({**counts, "failures": tally.failures}, indent=1))
    return 0 if tally.bad() == 0 and not tally.failures else 1


if __name__ == "__main__":
    sys.exit(main())
