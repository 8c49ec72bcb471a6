"""The rule that chooses between two trainings on the val split (issue 40, "Choose by the worst case"), written
down before training and applied by code, not by eye.

A candidate checkpoint replaces the incumbent (the shipped weights, or the previous stage) when, on the same val
clips, scored by ``evaluate_model`` with the ``demod-jbu`` baseline (``EvalOptions``'s default baseline):

1. its smallest per-clip margin over ``demod-jbu`` (``margin_min``) does not fall;
2. its count of artifact pixels (``artifact_pixels``: tonemapped error above ``metrics.ARTIFACT_ERROR`` where
   ``demod-jbu``'s is below ``metrics.ARTIFACT_BASELINE``) does not rise;
3. its mean PSNR, SSIM and tPSNR do not fall.

Ties count as "does not fall/rise" to the rounding of ``TOLERANCE`` (PSNR and margins in dB to 0.005, SSIM to
5e-5), so two scorings of the same weights always choose the incumbent's equal. The test split never enters."""
from __future__ import annotations

from dataclasses import dataclass

#: Rounding below which two scores are equal: dB for PSNR, tPSNR and margins, unitless for SSIM.
TOLERANCE = {"margin_min": 0.005, "psnr": 0.005, "ssim": 5e-5, "tpsnr": 0.005}


@dataclass(frozen=True)
class Choice:
    """The rule's verdict: ``replace`` when every line holds; ``reasons``: each line that failed, in words."""
    replace: bool
    reasons: tuple[str, ...]

    def line(self, label: str) -> str:
        """'LABEL: val rule replaces the shipped weights' or '... keeps the shipped weights: REASON; REASON'."""
        return (f"{label}: val rule {'replaces' if self.replace else 'keeps'} the shipped weights"
                + ("" if self.replace else ": " + "; ".join(self.reasons)))

    def record(self, forced: bool) -> dict:
        """The verdict as a weights JSON keeps it."""
        return {"replace": self.replace, "reasons": list(self.reasons), "forced": forced}


def choose(candidate: dict, incumbent: dict) -> Choice:
    """Apply the rule to two ``evaluate_model`` results (their ``mean``) on the same val clips."""
    c, i = candidate["mean"], incumbent["mean"]
    reasons = []
    for key, name in (("margin_min", "smallest per-clip margin over demod-jbu"), ("psnr", "mean PSNR"),
                      ("ssim", "mean SSIM"), ("tpsnr", "mean tPSNR")):
        if c.get(key) is None or i.get(key) is None:
            reasons.append(f"{name} is missing (score both with the demod-jbu baseline on clips of 2+ frames)")
        elif c[key] < i[key] - TOLERANCE[key]:
            reasons.append(f"{name} falls: {c[key]:.4g} against {i[key]:.4g}")
    ca, ia = c.get("artifact_pixels"), i.get("artifact_pixels")
    if ca is None or ia is None:
        reasons.append("artifact pixels are missing (score both with the demod-jbu baseline)")
    elif ca > ia:
        reasons.append(f"artifact pixels rise: {ca} against {ia}")
    return Choice(not reasons, tuple(reasons))
