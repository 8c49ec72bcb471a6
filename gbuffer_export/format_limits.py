"""The export formats and what their consumers take, declared once (``blendsr export-dataset --format``).

Each row says which clip buffers an export needs, which LR levels and which HR size the consumer's reader loads
(docs/formats.md gives the evidence for each). Every shell reads this table: ``export-dataset`` refuses a clip
that breaks a limit before any file is written (``check_clips``: one line naming the clip, the consumer and the
fix); ``blendsr --help``, ``render --help``, ``dataset --dry-run`` and the add-on list the formats and what each
needs (``needs_text``); ``--for-formats`` and the spec key ``for_formats`` render what the formats need
(``render_for_formats``, the one derivation). Pure Python: no bpy, no torch.
"""
from __future__ import annotations

from dataclasses import dataclass

from .conventions import ALL_BUFFERS
from .errors import BlendSRError


class FormatLimitError(BlendSRError):
    """A clip or a render setting that the consumer of an export format cannot load (one line naming the fix)."""


@dataclass(frozen=True)
class ExportFormat:
    name: str                               # the --format value
    title: str                              # as messages name it
    consumer: str                           # the reader that loads the export
    buffers: tuple[str, ...]                # clip buffers an export needs (refused without)
    read_buffers: tuple[str, ...] = ()      # buffers the consumer's shipped configs read (a warning when absent)
    scales: tuple[float, ...] = ()          # LR levels (scales) the reader loads (refused without)
    why_scales: str = ""
    hr_size: tuple[int, int] | None = None  # the only HR size the reader loads
    why_size: str = ""

    def needs(self) -> str:
        """What a clip needs for this format, in one phrase (help texts, the dry run, the add-on)."""
        parts = []
        if self.scales:
            parts.append(" and ".join(f"a {s:g}x LR level" for s in self.scales))
        if self.hr_size:
            parts.append(f"HR {self.hr_size[0]}x{self.hr_size[1]}")
        parts.append("buffers " + ",".join(self.buffers + self.read_buffers))
        return ", ".join(parts)


FORMATS: dict[str, ExportFormat] = {f.name: f for f in (
    ExportFormat("nss", "NSS", "Arm's NSS converter (safetensors_writer, reader NSSv1_0_1)",
                 buffers=("radiance", "depth", "motion"), scales=(2.0,),
                 why_scales="Arm's converter reads x2/ only"),
    ExportFormat("nfru", "NFRU", "Arm's NFRU converter (reader NFRUv2_2)",
                 buffers=("radiance", "depth", "motion"), scales=(2.0,),
                 why_scales="Arm's NFRU reader reads x2/ only",
                 hr_size=(1920, 1080),
                 why_size="Arm's NFRU reader loads only 1920x1080 captures (it stacks a fixed 960x540 motion)"),
    ExportFormat("rdg", "RDG", "the RDG authors' loader (basicsr/data/render_dataset.py)",
                 buffers=("radiance",), read_buffers=("normal", "fbeta", "motion", "depth")),
)}
NAMES: tuple[str, ...] = tuple(FORMATS)


def names_text() -> str:
    """'nss, nfru, rdg' (``blendsr --help``)."""
    return ", ".join(NAMES)


def needs_text(names=NAMES) -> str:
    """'nss: a 2x LR level, buffers radiance,depth,motion; nfru: ...' for the formats ``names``."""
    return "; ".join(f"{n}: {FORMATS[n].needs()}" for n in names)


def parse_formats(names, where: str = "--for-formats") -> tuple[str, ...]:
    """Format names (a list, or 'nss,rdg') checked against the table, in the table's order; one line naming
    ``where`` otherwise."""
    if isinstance(names, str):
        names = names.split(",")
    got = [str(n).strip().lower() for n in names if str(n).strip()]
    for n in got:
        if n not in FORMATS:
            raise FormatLimitError(f"{where}: unknown format {n!r}; choose from {names_text()}")
    return tuple(n for n in NAMES if n in got)


def _scales_text(scales) -> str:
    return ", ".join(f"{s:g}" for s in scales)


def clip_problem(fmt: str, clip) -> str:
    """'' when ``clip`` (an open clip) can become an export that ``fmt``'s consumer loads, else one line naming the
    clip, the format, the limit and the fix."""
    f = FORMATS[fmt]
    missing = [b for b in f.buffers if b not in clip.buffers]
    if missing:
        return (f"{clip.path}: {f.title} needs the buffers {', '.join(f.buffers)} (clip has "
                f"{', '.join(clip.buffers)}); render it with --buffers {','.join(f.buffers)} or more, or "
                f"--for-formats {fmt}")
    if not clip.frames:
        return f"{clip.path}: no finished frames"
    for s in f.scales:
        if not any(abs(c - s) < 1e-9 for c in clip.scales):
            return (f"{clip.path}: {f.title} needs a {s:g}x level ({f.why_scales}) and the clip has scale(s) "
                    f"{_scales_text(clip.scales)}; render it with --scales {s:g},4 or --for-formats {fmt} (a "
                    f"dataset spec: scale = {s:g} and scales = [{s:g}, 4] in its [render] table, or "
                    f"for_formats = [\"{fmt}\"] in its [dataset] table)")
    if f.hr_size and tuple(clip.sizes["hr"]) != tuple(f.hr_size):
        w, h = clip.sizes["hr"]
        return (f"{clip.path}: {f.title} needs HR {f.hr_size[0]}x{f.hr_size[1]} ({f.why_size}) and the clip is "
                f"{w}x{h}; render it with --hr-size {f.hr_size[0]}x{f.hr_size[1]} or --for-formats {fmt}")
    return ""


def check_clips(fmt: str, clips, error: type[BlendSRError] = FormatLimitError) -> None:
    """``error`` (FormatLimitError) for the first clip of ``clips`` that ``fmt``'s consumer cannot load
    (``clip_problem``), before anything is written."""
    for clip in clips:
        line = clip_problem(fmt, clip)
        if line:
            raise error(line)


def render_problem(fmt: str, render: dict) -> str:
    """'' when a clip rendered with ``render`` (a dataset job's settings: scale, scales, hr_size, buffers) can be
    exported as ``fmt``, else what it lacks in a few words ('no 2x level', 'HR 640x360, not 1920x1080', 'buffers
    depth')."""
    f = FORMATS[fmt]
    scales = [float(s) for s in (render.get("scales") or (render["scale"],))]
    out = [f"no {s:g}x level" for s in f.scales if not any(abs(s - c) < 1e-9 for c in scales)]
    size = tuple(render.get("hr_size") or ())
    if f.hr_size and size != tuple(f.hr_size):
        out.append(f"HR {'x'.join(map(str, size)) or 'the scene size'}, not {f.hr_size[0]}x{f.hr_size[1]}")
    lacking = [b for b in f.buffers if b not in render.get("buffers", ())]
    if lacking:
        out.append(f"no {','.join(lacking)}")
    return "; ".join(out)


def formats_report(renders) -> list[str]:
    """One line per format: whether every clip of ``renders`` (job render settings) can be exported as it, and
    otherwise how many cannot, why, and the fix (``blendsr dataset --dry-run``)."""
    renders = list(renders)
    lines = []
    for n, f in FORMATS.items():
        bad = [p for p in (render_problem(n, r) for r in renders) if p]
        if not bad:
            lines.append(f"export {n}: every clip can be exported ({f.needs()})")
        else:
            lines.append(f"export {n}: {len(bad)} of {len(renders)} clips cannot be ({bad[0]}); {f.title} needs "
                         f"{f.needs()}: add for_formats = [\"{n}\"] to the spec's [dataset] table or pass "
                         f"--for-formats {n}")
    return lines


def render_for_formats(formats, *, scales, hr_size, buffers, where: str = "--for-formats") -> dict:
    """The render settings that give clips every format of ``formats`` loads: ``scales`` (the clip's, its first
    the 'lr' level) with each LR level a format reads added after them, ``hr_size`` set to the size a format
    requires, ``buffers`` (names) with every buffer the formats need or their consumers read added, in the canonical
    order. Returns {scales, hr_size, buffers}; FormatLimitError naming ``where`` when a setting given conflicts
    (another HR size than a format's, two formats requiring different sizes)."""
    scales = [float(s) for s in scales]
    need_bufs = set(buffers)
    size = tuple(hr_size) if hr_size is not None else None
    for n in parse_formats(formats, where):
        f = FORMATS[n]
        scales += [s for s in f.scales if not any(abs(s - c) < 1e-9 for c in scales)]
        need_bufs.update(f.buffers + f.read_buffers)
        if f.hr_size:
            if size is not None and size != tuple(f.hr_size):
                raise FormatLimitError(f"{where} {n}: {f.why_size}, and the HR size is {size[0]}x{size[1]}; "
                                       f"render at {f.hr_size[0]}x{f.hr_size[1]} (or leave the size out)")
            size = tuple(f.hr_size)
    return {"scales": tuple(scales), "hr_size": size,
            "buffers": tuple(b for b in ALL_BUFFERS if b in need_bufs)}


__all__ = ["ExportFormat", "FORMATS", "FormatLimitError", "NAMES", "check_clips", "clip_problem", "formats_report",
           "names_text", "needs_text", "parse_formats", "render_for_formats", "render_problem"]
