"""Real takes whose labels name anatomical landmarks: joint centres by the standard definitions, and the fit
scored against them, the model's variants side by side.

    python -m bench.realanat                           # markdown to stdout (a note when the folder is absent)
    python -m bench.realanat --variants map '{"data_weight": "effective"}'   # rigid.Params as JSON
    python -m bench.realanat --raw RAW.json            # also every joint's error

The labels are read by this bench alone, to make the references; the fit never sees what they mean. The
references are the definitions a gait lab uses (ISB: Wu et al. 2002, 2005): a knee at the midpoint of the femoral
epicondyles, an ankle of the malleoli, an elbow of the humeral epicondyles, a wrist of the radial and ulnar
styloids, and a hip by Harrington et al. (2007)'s regression from the four iliac spines (pelvis axes: origin
midway between the ASISs, z towards the right one, x forward in the plane of the ASISs and the PSISs' midpoint,
y up; x = -0.24 PD - 9.9, y = -0.30 PW - 10.9, z = +-(0.33 PW + 7.3) mm, PW the ASISs' distance, PD from their
midpoint to the PSISs'). A regression hip is good to 10-20 mm, a midpoint to 5-10 mm of where the joint turns:
another solution, not the truth, as the references of ``../shared/realref/``. These takes were never used to
choose a setting: they are the real checking half.

A reference joint is matched to one of the fit's joints (a segment's origin, posed by the IK, in the take's own
frame and frames) by the assignment of least mean distance, under 100 mm (as ``../shared/realref/score.py``
does); its error is the rms distance over the frames both are seen.
"""
from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from bench.common import REPO, table

REALDATA = REPO.parent / "shared" / "realdata"
MATCH_MM = 100.0

#: (take under ../shared/realdata/, its landmarks): "hip" the four iliac spines (left and right ASIS, left and
#: right PSIS; one sacral marker for both PSISs), each other joint's two landmarks.
_BIOBUDDY_FUNC = {"hip": ("LASIS", "RASIS", "LPSIS", "RPSIS"), "LKJC": ("LLFE", "LMFE"), "RKJC": ("RLFE", "RMFE"),
                  "LAJC": ("LLM", "LSPH"), "RAJC": ("RLM", "RSPH"), "LEJC": ("LLHE", "LMHE"), "REJC": ("RLHE", "RMHE"),
                  "LWJC": ("LUS", "LRS"), "RWJC": ("RUS", "RRS")}
_BIOBUDDY_LOWER = {"hip": ("LASI", "RASI", "LPSI", "RPSI"), "LKJC": ("LKNE", "LKNEM"), "RKJC": ("RKNE", "RKNEM"),
                   "LAJC": ("LANK", "LANKM"), "RAJC": ("RANK", "RANKM")}
TAKES: dict[str, dict] = {
    "ezc3d/Qualisys.c3d": {"hip": ("L_IAS", "R_IAS", "L_IPS", "R_IPS"), "LKJC": ("L_FLE", "L_FME"),
                           "RKJC": ("R_FLE", "R_FME"), "LAJC": ("L_FAL", "L_TAM"), "RAJC": ("R_FAL", "R_TAM"),
                           "LEJC": ("L_HLE", "L_HME"), "REJC": ("R_HLE", "R_HME"), "LWJC": ("L_RSP", "L_UHE"),
                           "RWJC": ("R_RSP", "R_UHE")},
    "biobuddy/functional_trials/right_hip.c3d": _BIOBUDDY_FUNC,
    "biobuddy/functional_trials/right_knee.c3d": _BIOBUDDY_FUNC,
    **{f"biobuddy/lower_limb_calibration/Test_func_{j}.c3d": _BIOBUDDY_LOWER
       for j in ("lhip", "lknee", "lankle", "rhip", "rknee", "rankle")},
    "biobuddy/lower_limb_calibration/functional_trunk.c3d": _BIOBUDDY_LOWER,
    "addbiomechanics/stairdown_markers.trc": {"hip": ("LASI", "RASI", "LPSI", "RPSI")},
    "addbiomechanics/levelground_ccw_fast_01_01.trc": {"hip": ("L_ASIS", "R_ASIS", "L_PSIS", "R_PSIS")},
    "opensim-models/subject01_walk1.trc": {"hip": ("L.ASIS", "R.ASIS", "V.Sacral", "V.Sacral"),
                                           "LWJC": ("L.Wrist.Med", "L.Wrist.Lat"), "RWJC": ("R.Wrist.Med", "R.Wrist.Lat")},
}


def harrington(lasi: np.ndarray, rasi: np.ndarray, lpsi: np.ndarray, rpsi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3) left and right hip centres (mm) by Harrington et al. 2007 from the iliac spines (F, 3) each."""
    mid_a, mid_p = 0.5 * (lasi + rasi), 0.5 * (lpsi + rpsi)
    z = rasi - lasi
    pw = np.linalg.norm(z, axis=1, keepdims=True)
    z = z / pw
    fwd = mid_a - mid_p
    x = fwd - np.sum(fwd * z, axis=1, keepdims=True) * z
    pd = np.linalg.norm(fwd, axis=1, keepdims=True)
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    base = mid_a + (-0.24 * pd - 9.9) * x + (-0.30 * pw - 10.9) * y
    side = (0.33 * pw + 7.3) * z
    return base - side, base + side


def references(points: np.ndarray, labels: list[str], marks: dict) -> dict[str, np.ndarray]:
    """{joint: (F, 3)} from the landmarks of ``marks`` that the take has (NaN where one is unseen)."""
    at = {lab: i for i, lab in enumerate(labels)}
    out = {}
    for joint, names in marks.items():
        if not all(n in at for n in names):
            continue
        p = [points[:, at[n]] for n in names]
        if joint == "hip":
            out["LHJC"], out["RHJC"] = harrington(*p)
        else:
            out[joint] = 0.5 * (p[0] + p[1])
    return out


def score(ours: np.ndarray, refs: dict[str, np.ndarray]) -> dict:
    """Match each reference joint to one of ``ours`` (F, K, 3) (least mean distance, under ``MATCH_MM``):
    {"matched", "of", "mean_mm" (rms over the matched), "each": {joint: rms mm or None}}."""
    from scipy.optimize import linear_sum_assignment

    names = list(refs)
    C = np.full((len(names), ours.shape[1]), 1e9)
    for j, n in enumerate(names):
        d = np.linalg.norm(ours - refs[n][:, None, :], axis=2)  # (F, K)
        ok = np.isfinite(d)
        C[j] = np.where(ok.any(0), np.nansum(np.where(ok, d, 0.0), 0) / np.maximum(ok.sum(0), 1), 1e9)
    rows, cols = linear_sum_assignment(C)
    each: dict[str, float | None] = {n: None for n in names}
    for j, k in zip(rows, cols):
        if C[j, k] < MATCH_MM:
            d = np.linalg.norm(ours[:, k] - refs[names[j]], axis=1)
            each[names[j]] = float(np.sqrt(np.nanmean(d**2)))
    got = [v for v in each.values() if v is not None]
    return {"matched": len(got), "of": len(names), "mean_mm": float(np.mean(got)) if got else None, "each": each}


def one_take(args: tuple[str, list[tuple[str, dict]]]) -> tuple[str, dict]:
    """Every variant's score on one take (the stages up to the joints shared)."""
    rel, variants = args
    from mocapskel import pipeline
    from mocapskel.model.kinematics import segment_origins
    from mocapskel.stages import rigid

    joints = pipeline.run_until(REALDATA / rel, "joints").artifact
    mk = joints.topology.segments.markers
    refs = references(mk.points, list(mk.labels), TAKES[rel])
    out = {"frames": int(mk.points.shape[0]), "markers": len(mk.labels)}
    for name, kw in variants:
        mot = pipeline.run_until(joints, "ik", {"rigid": rigid.Params(**kw)}).artifact
        out[name] = score(segment_origins(mot), refs)
    return rel, out


def _variant(text: str) -> tuple[str, dict]:
    if text == "map":
        return text, {}
    return text, json.loads(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="+", default=["map"],
                    help="map (rigid.Params' defaults), or rigid.Params keywords as JSON")
    ap.add_argument("--takes", nargs="+", default=list(TAKES), help="takes under ../shared/realdata/")
    ap.add_argument("--raw", help="write every score here (JSON)")
    a = ap.parse_args()
    if not REALDATA.is_dir():
        print(f"../shared/realdata/ is absent: nothing measured ({REALDATA})")
        return
    variants = [_variant(v) for v in a.variants]
    names = [n for n, _ in variants]
    takes = [t for t in a.takes if (REALDATA / t).exists()]
    for t in set(a.takes) - set(takes):
        print(f"  {t}: ABSENT", file=sys.stderr)
    with ProcessPoolExecutor(2) as ex:
        got = dict(ex.map(one_take, [(t, variants) for t in takes]))
    rows = []
    for t in takes:
        g = got[t]
        rows.append([t, g[names[0]]["of"]] + [f"{g[n]['matched']}: {g[n]['mean_mm']:.1f}" if g[n]["mean_mm"] is not None
                                             else "0" for n in names])
        print(t, {n: {k: (round(v, 1) if v is not None else None) for k, v in g[n]["each"].items()} for n in names},
              file=sys.stderr)
    # over every reference joint that all variants matched: the same joints for each
    both = [(t, j) for t in takes for j in got[t][names[0]]["each"]
            if all(got[t][n]["each"][j] is not None for n in names)]
    total = [sum(got[t][n]["matched"] for t in takes) for n in names]
    of = sum(got[t][names[0]]["of"] for t in takes)
    rows.append([f"all ({len(both)} joints every variant matched)", of]
                + [f"{m}: {np.mean([got[t][n]['each'][j] for t, j in both]):.1f}" for n, m in zip(names, total)])
    print(table(["take", "reference joints"] + [f"{n}: matched, mean rms (mm)" for n in names], rows))
    if a.raw:
        Path(a.raw).write_text(json.dumps(got, indent=1))


if __name__ == "__main__":
    main()
