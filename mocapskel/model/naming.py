"""Names for the fitted skeleton: humanoid recognition without a template.

:func:`name_skeleton` looks at the fitted tree and its proportions alone. A
tree is taken for a person when it is a trunk (a path of 1-4 segments) with
five end chains: a head (1-2 segments, the shortest) and four limbs of 2-4
segments, the legs at one end of the trunk, the arms and the head at the other
(or all five on a one-segment trunk: then the head is the shortest chain and
the legs the two longest of the rest), each pair of limbs alike in length
(within a factor 1.5). Left and right come from the geometry over the take:
the feet point forward and the knees bend backward, which tells forward from
backward, and with the trunk's up and the line between the hips, left from
right; L/R label prefixes (``LTHI``, ``L_FLE``, ``LeftKnee``...) of the limbs'
markers decide instead where they are consistent. Nothing depends on the
marker set or the number of markers.

Humanoid names (the convention of the common retargeting tools)::

    Hips (the pelvis: the BVH root)
      Spine [Chest [UpperChest]]      trunk segments above the pelvis
        [Neck] Head
        [LeftShoulder] LeftArm LeftForeArm [LeftHand]   (and Right...)
      LeftUpLeg LeftLeg [LeftFoot [LeftToeBase]]      (and Right...)

A 3-segment arm is [LeftShoulder] LeftArm LeftForeArm when its first segment
is much shorter than its second (a clavicle, under 0.7 of the upper arm),
else LeftArm LeftForeArm LeftHand. Joint centres are named after the joint
(``LeftKnee``, ``LeftHip``, ``Lumbar`` ...); other subjects get
``<parent>_<child>``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

import numpy as np

from .kinematics import segment_origins
from .tree import sanitize_names

__all__ = ["Naming", "NotPerson", "name_skeleton", "segment_names", "SCHEMES", "JOINT_OF"]

SCHEMES = ("auto", "humanoid", "segments")

#: Anatomical joint of each humanoid bone (the joint at the bone's start, with its parent).
JOINT_OF: dict[str, str] = {
    "Spine": "Lumbar", "Chest": "Thoracic", "UpperChest": "UpperThoracic", "Neck": "LowerNeck",
    "UpLeg": "Hip", "Leg": "Knee", "Foot": "Ankle", "ToeBase": "Toe",
    "Shoulder": "Sternoclavicular", "Arm": "Shoulder", "ForeArm": "Elbow", "Hand": "Wrist",
}  # fmt: skip

_SIDE_RE = {
    "L": re.compile(r"^(?:L(?=[A-Z0-9_.\-])|Left|left|LEFT|l_)"),
    "R": re.compile(r"^(?:R(?=[A-Z0-9_.\-])|Right|right|RIGHT|r_)"),
}


@dataclass(frozen=True)
class Naming:
    """How the segments of a skeleton are named.

    scheme      : "humanoid" or "segments".
    names       : (S,) BVH joint name of each segment.
    joint_names : (S,) name of each segment's joint with its parent in the
                  fitted tree (the root's: ""), for joint-centre points.
    root        : the segment the BVH is rooted at (the pelvis for a humanoid).
    hips_children : for a humanoid, the two leg segments (their joints with the
                  pelvis place the root between them), else ().
    side_from   : "labels", "geometry" or "" (not humanoid).
    note        : why the tree was or was not taken for a person.
    """

    scheme: str
    names: tuple[str, ...]
    joint_names: tuple[str, ...]
    root: int
    hips_children: tuple[int, ...] = ()
    side_from: str = ""
    note: str = ""
    roles: dict = field(default_factory=dict)

    @property
    def humanoid(self) -> bool:
        return self.scheme == "humanoid"

    def report(self) -> dict:
        return {"scheme": self.scheme, "root": self.names[self.root], "side_from": self.side_from or None,
                "note": self.note}


class NotPerson(str):
    """Why a tree is not taken for a person (the text), and, when it is a person's but for its two legs or
    its two arms, which differ in length or in number of segments: ``limbs`` = (``"legs"`` or ``"arms"``,
    the segments of one limb's chain from the trunk, those of the other's, their lengths in mm), else None."""

    limbs: tuple | None

    def __new__(cls, text: str, limbs: tuple | None = None) -> "NotPerson":
        out = super().__new__(cls, text)
        out.limbs = limbs
        return out


def _neighbours(parent: np.ndarray) -> list[list[int]]:
    nb: list[list[int]] = [[] for _ in range(len(parent))]
    for s, p in enumerate(parent.tolist()):
        if p >= 0:
            nb[s].append(p)
            nb[p].append(s)
    return nb


def generic(skel, note: str = "") -> Naming:
    """Today's names: segment names, joints ``<parent>_<child>``, the fitted root."""
    names = tuple(skel.names)
    par = np.asarray(skel.parent)
    jn = tuple(f"{names[p]}_{names[s]}" if p >= 0 else "" for s, p in enumerate(par.tolist()))
    root = int(np.flatnonzero(par < 0)[0])
    return Naming("segments", names, jn, root, note=note)


def _chains(nb: list[list[int]]) -> tuple[list[list[int]], list[int]] | str:
    """End chains (attachment first) and their attachment nodes, or why there are none."""
    S = len(nb)
    deg = np.array([len(n) for n in nb])
    leaves = [s for s in range(S) if deg[s] == 1]
    chains, attach = [], []
    for leaf in leaves:
        chain = [leaf]
        prev, cur = leaf, nb[leaf][0]
        while deg[cur] == 2:
            chain.append(cur)
            prev, cur = cur, next(n for n in nb[cur] if n != prev)
        if deg[cur] < 3:
            return "the tree is a single chain"
        chains.append(chain[::-1])
        attach.append(cur)
    return chains, attach


def _rest_joint(skel, a: int, b: int) -> np.ndarray:
    """Rest position of the joint between adjacent segments a and b (whichever way the tree points)."""
    return skel.origin[b] if skel.parent[b] == a else skel.origin[a]


def _segment_lengths(skel, chain: list[int], attach: int) -> list[float]:
    """Each chain segment's length at rest: joint to next joint, the last to its End Site.

    Independent of where the fitted tree is rooted (unlike ``bone_length``).
    """
    out = []
    prev = attach
    for k, s in enumerate(chain):
        start = _rest_joint(skel, prev, s)
        if k + 1 < len(chain):
            out.append(float(np.linalg.norm(_rest_joint(skel, s, chain[k + 1]) - start)))
        else:
            out.append(float(np.linalg.norm(skel.end_site[s])))
        prev = s
    return out


def _label_side(labels: list[str]) -> str | None:
    votes = {"L": 0, "R": 0}
    for lab in labels:
        for side, rx in _SIDE_RE.items():
            if rx.match(lab):
                votes[side] += 1
    n = len(labels)
    if n and votes["L"] >= 0.8 * n and votes["R"] == 0:
        return "L"
    if n and votes["R"] >= 0.8 * n and votes["L"] == 0:
        return "R"
    return None


def _joint_points(motion, frames: np.ndarray) -> np.ndarray:
    sub = _subsample(motion, frames)
    return segment_origins(sub)


def _subsample(motion, frames: np.ndarray):
    return replace(motion, root_pos=motion.root_pos[frames], rot=motion.rot[frames])


def name_skeleton(skel, motion=None, scheme: str = "auto") -> Naming:
    """Name a skeleton's segments (see the module docstring).

    Parameters
    ----------
    skel : Skeleton
    motion : Motion, optional
        The take's motion: left/right from geometry need it (without it, and
        without L/R labels, the tree is not taken for a person).
    scheme : {"auto", "humanoid", "segments"}
        "segments": the generic names; "auto" and "humanoid": humanoid names
        when the tree is recognised, else the generic names with a note.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}")
    if scheme == "segments":
        return generic(skel, "generic names asked for (--names segments)")
    why = recognise(skel, motion)
    if isinstance(why, str):
        return generic(skel, f"not recognised as a person: {why}")
    return why


def recognise(skel, motion=None) -> Naming | str:
    """The humanoid naming of ``skel``, or the reason it is not taken for a person (a :class:`NotPerson`
    where its limbs say which)."""
    par = np.asarray(skel.parent)
    S = len(par)
    if S < 7:
        return f"{S} segments (a person has a trunk, a head and four limbs: 7 or more)"
    nb = _neighbours(par)
    got = _chains(nb)
    if isinstance(got, str):
        return got
    chains, attach = got
    if len(chains) != 5:
        return f"{len(chains)} end chains (a person has 5: head, two arms, two legs)"
    in_chain = {s for c in chains for s in c}
    trunk = [s for s in range(S) if s not in in_chain]
    tnb = {s: [n for n in nb[s] if n in trunk] for s in trunk}
    if any(len(v) > 2 for v in tnb.values()):
        return "the segments between the limbs branch (a person's trunk is a chain)"
    if len(trunk) > 4:
        return f"a trunk of {len(trunk)} segments (1-4 expected)"
    ends = [s for s in trunk if len(tnb[s]) <= 1]
    order = [ends[0]]
    while len(order) < len(trunk):
        order.append(next(n for n in tnb[order[-1]] if n not in order))
    seg_len = [_segment_lengths(skel, c, a) for c, a in zip(chains, attach)]
    length = [float(sum(x)) for x in seg_len]
    ids = list(range(5))
    if len(trunk) == 1:
        head = min(ids, key=lambda i: length[i])
        rest = sorted((i for i in ids if i != head), key=lambda i: -length[i])
        legs, arms = rest[:2], rest[2:]
        pelvis = top = trunk[0]
    else:
        at = {e: [i for i in ids if attach[i] == e] for e in (order[0], order[-1])}
        if sum(len(v) for v in at.values()) != 5:
            return "limbs attached to the middle of the trunk"
        lo = next((e for e in at if len(at[e]) == 2), None)
        if lo is None:
            return "no end of the trunk carries exactly two limbs"
        hi = order[-1] if lo == order[0] else order[0]
        if len(at[hi]) != 3:
            return "no end of the trunk carries the head and two arms"
        legs = at[lo]
        head = min(at[hi], key=lambda i: length[i])
        arms = [i for i in at[hi] if i != head]
        pelvis, top = lo, hi
        if order[0] != pelvis:
            order = order[::-1]
    if not 1 <= len(chains[head]) <= 2:
        return f"a head chain of {len(chains[head])} segments"
    if len(chains[head]) == 2 and not _farther_from(skel, pelvis, chains[head][1], chains[head][0]):
        return "the end of the head chain is nearer the pelvis than its first segment (not a neck and a head)"
    for pair, what in ((legs, "legs"), (arms, "arms")):
        a, b = length[pair[0]], length[pair[1]]
        limbs = (what, tuple(chains[pair[0]]), tuple(chains[pair[1]]), a, b)
        if any(not 2 <= len(chains[i]) <= 4 for i in pair):
            counts = [len(chains[i]) for i in pair]
            return NotPerson(f"{what} of {counts} segments (2-4 expected)", limbs if counts[0] != counts[1] else None)
        if not (min(a, b) > 0 and max(a, b) <= 1.5 * min(a, b)):
            return NotPerson(f"{what} of unequal length ({a:.0f} and {b:.0f} mm)", limbs)
        if len(chains[pair[0]]) != len(chains[pair[1]]):
            return NotPerson(f"{what} of {len(chains[pair[0]])} and {len(chains[pair[1]])} segments", limbs)
    if length[head] >= min(length[i] for i in legs + arms):
        return "the head chain is not shorter than the limbs"
    if len(trunk) == 1 and min(length[i] for i in legs) < max(length[i] for i in arms):
        return "legs and arms cannot be told apart"

    side = _sides(skel, motion, chains, attach, legs, arms, pelvis)
    if isinstance(side, str):
        return side
    (left_leg, right_leg, left_arm, right_arm), side_from = side

    names = [""] * S
    role: dict[int, str] = {}
    names[pelvis] = "Hips"
    spine_names = {1: ["Spine"], 2: ["Spine", "Chest"], 3: ["Spine", "Chest", "UpperChest"]}
    for s, n in zip(order[1:], spine_names.get(len(order) - 1, [])):
        names[s] = n
    head_chain = chains[head]
    for s, n in zip(head_chain, ["Head"] if len(head_chain) == 1 else ["Neck", "Head"]):
        names[s] = n
    leg_parts = ["UpLeg", "Leg", "Foot", "ToeBase"]
    for ci, side_name in ((left_leg, "Left"), (right_leg, "Right")):
        for s, n in zip(chains[ci], leg_parts):
            names[s] = side_name + n
    for ci, side_name in ((left_arm, "Left"), (right_arm, "Right")):
        c = chains[ci]
        if len(c) == 4 or (len(c) == 3 and seg_len[ci][0] < 0.7 * seg_len[ci][1]):
            parts = ["Shoulder", "Arm", "ForeArm", "Hand"]
        else:
            parts = ["Arm", "ForeArm", "Hand"]
        for s, n in zip(c, parts):
            names[s] = side_name + n
    if any(not n for n in names):  # pragma: no cover - every segment is in the trunk or a chain
        return "a segment has no place in a person"
    role = {s: names[s] for s in range(S)}
    joint_names = []
    for s, p in enumerate(par.tolist()):
        if p < 0:
            joint_names.append("")
            continue
        # the joint between s and p, named after the segment further from the pelvis
        far = s if _depth_from(pelvis, nb)[s] > _depth_from(pelvis, nb)[p] else p
        n = names[far]
        sd = "Left" if n.startswith("Left") else "Right" if n.startswith("Right") else ""
        base = n[len(sd):]
        joint_names.append(sd + JOINT_OF.get(base, "Neck" if base == "Head" and len(head_chain) == 1 else
                                             "UpperNeck" if base == "Head" else base))
    legs_seg = (chains[left_leg][0], chains[right_leg][0])
    note = f"recognised as a person ({len(trunk)}-segment trunk, legs of {len(chains[legs[0]])}, arms of {len(chains[arms[0]])} segments; left/right from {side_from})"
    return Naming("humanoid", tuple(names), tuple(joint_names), int(pelvis), legs_seg, side_from, note, role)


def _farther_from(skel, root: int, a: int, b: int) -> bool:
    """Whether segment ``a``'s markers sit farther from segment ``root``'s origin than ``b``'s, in the rest pose."""
    seg = np.asarray(skel.marker_segment)
    pos = np.asarray(skel.origin)[np.maximum(seg, 0)] + np.asarray(skel.marker_local)

    def dist(s: int) -> float:
        p = pos[(seg == s) & np.isfinite(pos).all(1)]
        return float(np.linalg.norm(p.mean(0) - skel.origin[root])) if len(p) else np.nan

    return bool(dist(a) > dist(b))


def _depth_from(root: int, nb: list[list[int]]) -> np.ndarray:
    depth = np.full(len(nb), -1)
    depth[root] = 0
    stack = [root]
    while stack:
        s = stack.pop()
        for n in nb[s]:
            if depth[n] < 0:
                depth[n] = depth[s] + 1
                stack.append(n)
    return depth


def _sides(skel, motion, chains, attach, legs, arms, pelvis):
    """(left leg, right leg, left arm, right arm) chain indices and where the sides came from."""
    labels = list(skel.labels)
    mseg = np.asarray(skel.marker_segment)

    def chain_labels(ci):
        return [labels[m] for m in np.flatnonzero(np.isin(mseg, chains[ci]))]

    by_label = {}
    for pair in (legs, arms):
        sides = [_label_side(chain_labels(i)) for i in pair]
        if sorted(s or "" for s in sides) == ["L", "R"]:
            by_label[tuple(pair)] = (pair[0], pair[1]) if sides[0] == "L" else (pair[1], pair[0])
    if len(by_label) == 2:
        ll, rl = by_label[tuple(legs)]
        la, ra = by_label[tuple(arms)]
        return (ll, rl, la, ra), "labels"
    if motion is None:
        return "no motion to tell left from right"
    F = motion.rot.shape[0]
    frames = np.unique(np.linspace(0, F - 1, min(F, 2000)).round().astype(int))
    P = _joint_points(motion, frames)  # (K, S, 3) joint points (a child's origin is its joint)
    rot = motion.rot[frames]
    par = np.asarray(skel.parent)

    def joint(a: int, b: int) -> np.ndarray:
        """The joint between adjacent segments a and b, every frame."""
        return P[:, b] if par[b] == a else P[:, a]

    def end(c: list[int], k: int) -> np.ndarray:
        """Where segment c[k] ends: its joint with c[k+1], or its end site."""
        if k + 1 < len(c):
            return joint(c[k], c[k + 1])
        s = c[k]
        return P[:, s] + np.einsum("kij,j->ki", rot[:, s], skel.end_site[s])

    A, B = legs
    hipA, hipB = joint(pelvis, chains[A][0]), joint(pelvis, chains[B][0])
    mid = 0.5 * (hipA + hipB)
    top = np.mean([joint(attach[i], chains[i][0]) for i in arms], axis=0)
    up = _unit(top - mid)
    lat = _unit(hipA - hipB)
    n = np.cross(up, lat)  # forward if A is the right leg, backward if it is the left
    evidence = np.zeros(len(frames))
    for ci in legs:
        c = chains[ci]
        hip, knee, ankle = joint(pelvis, c[0]), end(c, 0), end(c, 1)
        t = _unit(knee - hip)
        v = ankle - knee
        k = v - np.sum(v * t, axis=1, keepdims=True) * t
        evidence -= np.sum(k * n, axis=1)  # the knee bends backward
        if len(c) >= 3:
            s = _unit(ankle - knee)
            fv = end(c, 2) - ankle
            fperp = fv - np.sum(fv * s, axis=1, keepdims=True) * s
            evidence += np.sum(fperp * n, axis=1)  # the foot points forward
    total = float(np.nansum(evidence))
    if not np.isfinite(total) or total == 0.0:
        return "left and right cannot be told from the motion"
    a_is_right = total > 0
    left_leg, right_leg = (B, A) if a_is_right else (A, B)
    left = lat if not a_is_right else -lat
    X, Y = arms
    shX = joint(attach[X], chains[X][0])
    shY = joint(attach[Y], chains[Y][0])
    x_left = float(np.nansum(np.sum((shX - shY) * left, axis=1))) > 0
    left_arm, right_arm = (X, Y) if x_left else (Y, X)
    out = [left_leg, right_leg, left_arm, right_arm]
    src = "geometry"
    for pair in (tuple(legs), tuple(arms)):  # labels win where they are consistent
        if pair in by_label:
            i = 0 if pair == tuple(legs) else 2
            if (out[i], out[i + 1]) != by_label[pair]:
                out[i], out[i + 1] = by_label[pair]
                src = "labels and geometry (they disagree; labels used)"
            else:
                src = "labels and geometry"
    return tuple(out), src


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


_TRAIL = re.compile(r"[\d_\-\s.]+$")


def segment_names(labels_per_segment: list[list[str]]) -> list[str]:
    """Names for segments from their markers' labels (common prefix), else generic."""
    names = []
    for i, labels in enumerate(labels_per_segment):
        pre = _common_prefix(labels) if labels else ""
        pre = _TRAIL.sub("", pre)
        if len(labels) == 1:
            pre = _TRAIL.sub("", labels[0])
        if len(pre) < 2 or re.fullmatch(r"[A-Za-z]?\d*", pre) or re.fullmatch(r"M\d*|Marker|marker|U|Unlabeled", pre):
            pre = f"seg{i:02d}"
        names.append(pre)
    return list(sanitize_names(names))


def _common_prefix(labels: list[str]) -> str:
    s1, s2 = min(labels), max(labels)
    i = 0
    while i < min(len(s1), len(s2)) and s1[i] == s2[i]:
        i += 1
    return s1[:i]
