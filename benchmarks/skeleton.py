"""Is the tracked skeleton right? Two figures per engine run for the benchmark report.

- How well the fitted skeleton explains the markers: the RMS residual of its solves [mm] (median, p90).
  Skin moves over bone and the model has no shoulder girdle, so ~10 mm is good; tens of mm mean a limb is
  mis-posed or carries another limb's markers.
- Whether each marker rides the segment its name says, for the naming conventions we can read (the
  CMU / HDM05 41-marker set and Plug-in Gait, which share their stems). The engine never reads names:
  this checks its calibration against what an operator would expect. Markers over a joint (SHO, ELB,
  KNE, ANK), whose segment is a matter of convention, are not judged.
"""

from __future__ import annotations

import re

import numpy as np

#: name stem (after the L/R side letter) -> segment stem; our 14 segments have no hands, so the wrist and
#: finger markers ride the forearm
_LIMB_STEMS = {
    "UPA": "upperarm", "FRM": "forearm", "WRA": "forearm", "WRB": "forearm", "FIN": "forearm",
    "THI": "thigh", "SHN": "shank", "TIB": "shank", "HEE": "foot", "TOE": "foot", "MT5": "foot",
}
_TRUNK_STEMS = {"FHD": "head", "BHD": "head", "FWT": "pelvis", "BWT": "pelvis", "ASI": "pelvis", "PSI": "pelvis"}
_TORSO = {"C7", "T10", "CLAV", "STRN", "RBAC", "RBAK"}


def expected_segment(name: str) -> str | None:
    """The segment a marker named `name` ("Subject:LWRA" or "LWRA") belongs on, or None if not judged."""
    marker = name.rpartition(":")[2].upper()
    if marker in _TORSO:
        return "torso"
    m = re.fullmatch(r"([LR])([A-Z0-9]+)", marker)
    if m is None:
        return None
    side, stem = m.groups()
    if stem in _TRUNK_STEMS:
        return _TRUNK_STEMS[stem]
    if stem in _LIMB_STEMS:
        return ("l_" if side == "L" else "r_") + _LIMB_STEMS[stem]
    return None


def misplaced(segments: dict[str, str]) -> tuple[int, list[str]]:
    """(markers judged, ["LWRA->l_upperarm", ...] those off their segment) of {marker name: segment}."""
    judged = {n: s for n, s in segments.items() if expected_segment(n) is not None}
    wrong = [f"{n.rpartition(':')[2]}->{s}" for n, s in judged.items() if s != expected_segment(n)]
    return len(judged), wrong


def residual_summary(rms_mm: np.ndarray) -> str:
    """"p50 / p90" of solve residuals [mm], or "–" without solves."""
    if len(rms_mm) == 0:
        return "–"
    return f"{np.median(rms_mm):.1f} / {np.percentile(rms_mm, 90):.1f}"
