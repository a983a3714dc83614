"""Joint and root motion of the synthetic human: range of motion, walking round a circle, and everyday
motions (walking, running and climbing along a line, reaching, kicking)."""
from __future__ import annotations

import numpy as np

from .body import _HINGE, _JNT, _S, JOINT_NAMES, _hinge_frame, _Subject
from .rotations import _matmul33, _mirror_axial, _rot_z, rotvec_to_matrix

# Joint motion. Ball joints: range (deg) of each rotation-vector component
# about the lab/rest axes X (forward), Y (left), Z (up), left side; the right
# side is the mirror image (X and Z components negated).
_ROM_BALL = {
    "Lumbar": ((-25, 25), (-20, 45), (-35, 35)),
    "Neck": ((-30, 30), (-40, 50), (-60, 60)),
    "LShoulder": ((-10, 90), (-120, 40), (-50, 50)),
    "LWrist": ((-25, 20), (-70, 60), (-60, 60)),
    "LHip": ((-20, 45), (-100, 25), (-35, 35)),
    "LAnkle": ((-20, 20), (-25, 45), (-20, 20)),
}


# --------------------------------------------------------------------------- motion


def _smooth(rng: np.random.Generator, t: np.ndarray, n: int, fmin: float, fmax: float, k: int = 4) -> np.ndarray:
    """(F, n) sums of ``k`` random sinusoids per column, frequencies in [fmin, fmax] Hz."""
    out = np.zeros((t.size, n))
    for _ in range(k):
        f = rng.uniform(fmin, fmax, n)
        ph = rng.uniform(0.0, 2.0 * np.pi, n)
        amp = rng.uniform(0.5, 1.0, n)
        out += amp * np.sin(2.0 * np.pi * np.outer(t, f) + ph)
    return out


def _rescale(x: np.ndarray, lo: np.ndarray | float, hi: np.ndarray | float) -> np.ndarray:
    """Map every column of ``x`` affinely onto exactly [lo, hi] (its min to lo, max to hi)."""
    mn, mx = x.min(0), x.max(0)
    span = np.where(mx > mn, mx - mn, 1.0)
    return lo + (np.asarray(hi) - lo) * (x - mn) / span


def _bump(phase: np.ndarray, centre: float, width: float) -> np.ndarray:
    """Periodic Gaussian bump over the gait cycle (phase in radians, centre/width in cycles)."""
    d = (phase / (2.0 * np.pi) - centre + 0.5) % 1.0 - 0.5
    return np.exp(-0.5 * (d / width) ** 2)


def _phase_envelope(rng: np.random.Generator, t: np.ndarray, n_groups: int, base: float) -> np.ndarray:
    """(F, G) smooth weights in [base, 1]: the groups take turns being exercised fully."""
    T = t[-1] + (t[1] - t[0] if t.size > 1 else 1.0)
    phase_len = min(8.0, T / n_groups)
    n_phase = int(np.ceil(T / phase_len))
    order = np.concatenate([rng.permutation(n_groups) for _ in range(n_phase // n_groups + 1)])[:n_phase]
    idx = np.minimum((t / phase_len).astype(int), n_phase - 1)
    ind = np.zeros((t.size, n_groups))
    ind[np.arange(t.size), order[idx]] = 1.0
    # smooth the switching: three moving averages over a ninth of a phase (C2, no jerks)
    dt = t[1] - t[0] if t.size > 1 else 1.0
    w = max(1, int(round(phase_len / 9.0 / dt)))
    for _ in range(3 if w > 1 else 0):
        c = np.cumsum(np.pad(ind, ((w // 2 + 1, w - 1 - w // 2), (0, 0)), mode="edge"), axis=0)
        ind = (c[w:] - c[:-w]) / w
    return base + (1.0 - base) * ind


def _rom_motion(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Range-of-motion take: every DoF covers its full range; joints take turns."""
    F = t.size
    groups = {"Lumbar": 0, "Neck": 0, "LShoulder": 1, "LElbow": 1, "LWrist": 1, "RShoulder": 2,
              "RElbow": 2, "RWrist": 2, "LHip": 3, "LKnee": 3, "LAnkle": 3, "RHip": 4, "RKnee": 4,
              "RAnkle": 4}  # fmt: skip
    env = _phase_envelope(rng, t, 5, base=0.25)
    rv = np.zeros((F, _S, 3))
    for e, name in enumerate(JOINT_NAMES):
        s = e + 1
        g = env[:, groups[name]][:, None]
        left = "L" + name[1:] if name[0] in "LR" else name
        if left in _HINGE:
            a, e1, e2 = _hinge_frame(name)
            lo, hi = _HINGE[left][1]
            x = _rescale(g * _smooth(rng, t, 1, 0.08, 0.5), lo, hi)[:, 0]
            y = _rescale(g * _smooth(rng, t, 2, 0.08, 0.5), -slack, slack)
            rv[:, s] = np.deg2rad(x[:, None] * a + y[:, :1] * e1 + y[:, 1:] * e2)
        else:
            rng_lohi = np.array(_ROM_BALL[left], float)
            if name.startswith("R"):
                rng_lohi[[0, 2]] = -rng_lohi[[0, 2], ::-1]
            x = _rescale(g * _smooth(rng, t, 3, 0.08, 0.5), rng_lohi[:, 0], rng_lohi[:, 1])
            rv[:, s] = np.deg2rad(x)
    # root: wander over the capture volume, turn around, tilt a little
    xy = _rescale(_smooth(rng, t, 2, 0.01, 0.08), -800.0, 800.0)
    z = subj.pelvis_height + _rescale(_smooth(rng, t, 1, 0.05, 0.3), 0.0, 50.0 * subj.pelvis_height / 995.0)[:, 0]
    yaw = np.deg2rad(_rescale(_smooth(rng, t, 1, 0.02, 0.08), -150.0, 150.0)[:, 0])
    tilt = np.deg2rad(_rescale(_smooth(rng, t, 2, 0.05, 0.3), np.array([-10.0, -10.0]), np.array([10.0, 20.0])))
    root_pos = np.column_stack([xy, z])
    root_rot = _matmul33(_rot_z(yaw), rotvec_to_matrix(np.column_stack([tilt, np.zeros(F)])))
    return root_pos, root_rot, rv


def _walk_motion(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Walking round a wobbly circle (~1.5 m radius) with random small extra motion."""
    F = t.size
    fc = rng.uniform(0.85, 0.95)  # strides per second
    phi0 = rng.uniform(0.0, 2.0 * np.pi)
    size = subj.pelvis_height / 995.0
    speed = 1100.0 * size * rng.uniform(0.9, 1.1)  # mm/s
    direction = rng.choice([-1.0, 1.0])
    radius = 1500.0 + 300.0 * _rescale(_smooth(rng, t, 1, 0.01, 0.05), -1.0, 1.0)[:, 0]
    alpha = rng.uniform(0.0, 2.0 * np.pi) + direction * speed / 1500.0 * t
    deg = np.deg2rad
    rv = np.zeros((F, _S, 3))
    for side, ph in (("L", 2.0 * np.pi * fc * t + phi0), ("R", 2.0 * np.pi * fc * t + phi0 + np.pi)):
        opp = ph + np.pi
        hip_flex = 10.0 + 20.0 * np.cos(ph - 0.85 * 2.0 * np.pi)
        arm_flex = 18.0 * np.cos(opp - 0.85 * 2.0 * np.pi)
        knee = 5.0 + 15.0 * _bump(ph, 0.12, 0.07) + 55.0 * _bump(ph, 0.72, 0.1)
        elbow = 25.0 + 10.0 * np.cos(opp - 0.85 * 2.0 * np.pi)
        ball = {
            "Hip": np.column_stack([3.0 + 4.0 * np.cos(ph), -hip_flex, 4.0 * np.sin(ph)]),
            "Ankle": np.column_stack([3.0 * np.sin(ph), 5.0 + 12.0 * np.sin(ph - 1.0), 2.0 * np.sin(ph)]),
            "Shoulder": np.column_stack([8.0 + 0 * ph, -arm_flex, 5.0 + 0 * ph]),
            "Wrist": np.column_stack([0 * ph, -10.0 + 3.0 * np.sin(ph), 0 * ph]),
        }
        for joint, v in ball.items():
            v = v + _smooth(rng, t, 3, 0.1, 0.6, k=3) * 1.0
            rv[:, JOINT_NAMES.index(side + joint) + 1] = deg(_mirror_axial(v) if side == "R" else v)
        for joint, ang in (("Knee", knee), ("Elbow", -elbow)):
            name = side + joint
            a, e1, e2 = _hinge_frame(name)
            y = _rescale(_smooth(rng, t, 2, 0.2, 1.0, k=3), -0.3 * slack, 0.3 * slack)
            rv[:, JOINT_NAMES.index(name) + 1] = deg(ang[:, None] * a + y[:, :1] * e1 + y[:, 1:] * e2)
    phL = 2.0 * np.pi * fc * t + phi0
    zero = np.zeros(F)
    lumbar = np.column_stack([2.0 * np.cos(phL), 5.0 + zero, -5.0 * np.sin(phL)])  # counter-rotation
    rv[:, 1] = deg(lumbar + _smooth(rng, t, 3, 0.1, 0.5, k=3))
    neck = np.column_stack([zero, zero, 5.0 * np.sin(phL)])  # keeps looking ahead, looks around
    rv[:, 2] = deg(neck + _smooth(rng, t, 3, 0.05, 0.3) * np.array([3.0, 4.0, 8.0]))
    pos = radius[:, None] * np.column_stack([np.cos(alpha), np.sin(alpha)])
    if F > 1:
        vel = np.gradient(pos, t, axis=0)
        heading = np.unwrap(np.arctan2(vel[:, 1], vel[:, 0]))
    else:
        heading = alpha + direction * np.pi / 2.0
    z = subj.pelvis_height - 15.0 * size + 12.0 * size * np.cos(2.0 * phL)
    root_pos = np.column_stack([pos, z])
    tilt = deg(np.column_stack([4.0 * np.cos(phL), 3.0 + 2.0 * np.sin(2.0 * phL), np.zeros(F)]))
    root_rot = _matmul33(_rot_z(heading + deg(5.0 * np.sin(phL))), rotvec_to_matrix(tilt))
    return root_pos, root_rot, rv


# ------------------------------------------------------------------ motions


def _minjerk_keys(t: np.ndarray, times: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(F, C) minimum-jerk interpolation through keyframes ``values`` (K, C) at ``times`` (K,)."""
    times = np.asarray(times, float)
    values = np.asarray(values, float)
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
    span = times[k + 1] - times[k]
    s = np.clip((t - times[k]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    w = s**3 * (10.0 - 15.0 * s + 6.0 * s * s)
    return values[k] + w[:, None] * (values[k + 1] - values[k])


def _put_ball(rv: np.ndarray, joint: str, v_deg: np.ndarray) -> None:
    """Set a ball joint from left-side-convention angles (deg, rotation vector components X, Y, Z)."""
    v = np.asarray(v_deg, float)
    rv[:, _JNT[joint] + 1] = np.deg2rad(_mirror_axial(v) if joint.startswith("R") else v)


def _put_hinge(rv: np.ndarray, joint: str, flex_deg: np.ndarray, slack_deg: np.ndarray) -> None:
    a, e1, e2 = _hinge_frame(joint)
    rv[:, _JNT[joint] + 1] = np.deg2rad(flex_deg[:, None] * a + slack_deg[:, :1] * e1 + slack_deg[:, 1:] * e2)


def _bumpc(phase_cycles: np.ndarray, centre: float, width: float) -> np.ndarray:
    d = (phase_cycles - centre + 0.5) % 1.0 - 0.5
    return np.exp(-0.5 * (d / width) ** 2)


_GAITS = {
    # f strides/s, stride (m, for a 995 mm pelvis), hip mean/amp, knee base, stance bump (h, c, w),
    # swing bump (h, c, w), ankle dorsi/plantar bumps, arm swing, elbow mean/amp, lumbar rot, lean, rise per stride
    # (walking elbows 30 +- 15 deg: in CMU's walks 07_01 and 07_12 the LUPA-LWRA distance varies by 6-7 mm (std)
    # and RUPA-RWRA by 11-12 mm; 22 +- 8 gave 2-4 mm, an arm stiffer than any real walk's)
    "walk": dict(f=(0.85, 0.95), stride=1.45, hip=(10, 20), knee0=4, kst=(15, 0.12, 0.07), ksw=(56, 0.72, 0.1),
                 dor=(10, 0.42, 0.1), pla=(20, 0.62, 0.06), arm=15, elb=(30, 15), rot=5, lean=3, rise=0.0, bob=12),
    "run": dict(f=(1.3, 1.4), stride=2.2, hip=(15, 27), knee0=15, kst=(25, 0.15, 0.07), ksw=(80, 0.64, 0.14),
                dor=(15, 0.18, 0.07), pla=(25, 0.42, 0.06), arm=35, elb=(85, 12), rot=10, lean=10, rise=0.0, bob=35),
    "climb": dict(f=(0.7, 0.8), stride=0.56, hip=(32, 28), knee0=10, kst=(55, 0.02, 0.12), ksw=(85, 0.72, 0.12),
                  dor=(12, 0.35, 0.1), pla=(15, 0.6, 0.07), arm=10, elb=(20, 6), rot=4, lean=10, rise=0.34, bob=15),
}


def _locomotion(kind: str, rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Walking, running or climbing stairs along a straight line."""
    g = _GAITS[kind]
    F = t.size
    size = subj.pelvis_height / 995.0
    f = rng.uniform(*g["f"])
    stride = g["stride"] * size * rng.uniform(0.93, 1.07) * 1000.0  # mm
    speed = stride * f
    cyc0 = rng.uniform()
    rv = np.zeros((F, _S, 3))
    zero = np.zeros(F)
    for side, off in (("L", 0.0), ("R", 0.5)):
        c = f * t + cyc0 + off  # gait cycle of this leg (0 = heel strike)
        ph = 2.0 * np.pi * c
        opp = ph + np.pi
        hip_flex = g["hip"][0] + g["hip"][1] * np.cos(ph)
        knee = g["knee0"] + g["kst"][0] * _bumpc(c, *g["kst"][1:]) + g["ksw"][0] * _bumpc(c, *g["ksw"][1:])
        dorsi = g["dor"][0] * _bumpc(c, *g["dor"][1:]) - g["pla"][0] * _bumpc(c, *g["pla"][1:])
        arm = g["arm"] * np.cos(opp)
        elbow = g["elb"][0] + g["elb"][1] * np.cos(opp)
        var = _smooth(rng, t, 3, 0.1, 0.6, k=3)  # stride-to-stride variability, ~±2 deg
        _put_ball(rv, side + "Hip", np.column_stack([2.0 + 3.0 * np.cos(ph), -hip_flex, 3.0 * np.sin(ph)]) + var)
        _put_ball(rv, side + "Ankle", np.column_stack([2.0 * np.sin(ph), -dorsi, 2.0 * np.sin(ph)]) + 0.5 * var)
        _put_ball(rv, side + "Shoulder", np.column_stack([8.0 + zero, -arm, 4.0 + zero]) + var)
        _put_ball(rv, side + "Wrist", np.column_stack([zero, -5.0 + 2.0 * np.sin(ph), zero]) + 0.5 * var)
        sl = _smooth(rng, t, 2, 0.2, 1.0, k=3) * 0.2 * slack
        _put_hinge(rv, side + "Knee", knee, sl)
        _put_hinge(rv, side + "Elbow", -elbow, sl)
    c = f * t + cyc0
    phL = 2.0 * np.pi * c
    _put_ball(rv, "Lumbar", np.column_stack([2.0 * np.cos(phL), g["lean"] + zero, -g["rot"] * np.sin(phL)])
              + _smooth(rng, t, 3, 0.1, 0.5, k=3))
    _put_ball(rv, "Neck", np.column_stack([zero, -0.6 * g["lean"] + zero, g["rot"] * np.sin(phL)])
              + _smooth(rng, t, 3, 0.05, 0.3) * np.array([2.0, 3.0, 6.0]))
    heading = rng.uniform(0.0, 2.0 * np.pi)
    d = np.array([np.cos(heading), np.sin(heading)])
    s = speed * (t - t.mean())
    lateral = 20.0 * size * np.sin(phL)
    xy = s[:, None] * d + lateral[:, None] * np.array([-d[1], d[0]])
    z = subj.pelvis_height - 15.0 * size + g["bob"] * size * np.cos(2.0 * phL) + g["rise"] * 1000.0 * size * f * t
    root_pos = np.column_stack([xy, z])
    tilt = np.deg2rad(np.column_stack([4.0 * np.cos(phL), 4.0 + 0.5 * g["lean"] + 2.0 * np.sin(2.0 * phL), zero]))
    root_rot = _matmul33(_rot_z(heading + np.deg2rad(g["rot"] * np.sin(phL))), rotvec_to_matrix(tilt))
    return root_pos, root_rot, rv


def _standing_root(rng: np.random.Generator, t: np.ndarray, subj: _Subject):
    F = t.size
    yaw = rng.uniform(0.0, 2.0 * np.pi) + np.deg2rad(2.0) * _smooth(rng, t, 1, 0.05, 0.2)[:, 0] / 2.0
    xy = rng.uniform(-500.0, 500.0, 2) + 10.0 * _smooth(rng, t, 2, 0.05, 0.3) / 2.0
    root_pos = np.column_stack([xy, np.full(F, subj.pelvis_height)])
    return root_pos, yaw


def _reach(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Standing; one or both arms reach to random targets and come back; the trunk leans and turns."""
    F, T = t.size, float(t[-1])
    # channels: per arm shoulder (x, y, z), elbow flex, wrist (x, y, z); lumbar (x, y, z); neck (x, y, z); hips flex
    rest = {"sh": [8.0, 0.0, 0.0], "el": 15.0, "wr": [0.0, 0.0, 0.0]}
    times, keys = [0.0], []
    el_times, el_keys = [0.0], [[rest["el"], rest["el"]]]  # elbows: they flex on the way out and back

    def pose(reach_l, reach_r, trunk, neck):
        row = []
        for r in (reach_l, reach_r):
            row += (r["sh"] + [r["el"]] + r["wr"]) if r else (rest["sh"] + [rest["el"]] + rest["wr"])
        return row + trunk + neck

    base = pose(None, None, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    keys.append(base)
    tk = rng.uniform(0.2, 0.6)
    while tk < T + 3.0:
        which = rng.choice(["L", "R", "LR"], p=[0.4, 0.4, 0.2])
        flex = rng.uniform(30.0, 160.0)
        abd = rng.uniform(0.0, 70.0)
        r = {"sh": [abd, -flex, rng.uniform(-30.0, 30.0)], "el": rng.uniform(5.0, 30.0),
             "wr": list(rng.uniform(-20.0, 20.0, 3))}
        lean = rng.uniform(0.0, 30.0) if flex < 90 else rng.uniform(-5.0, 10.0)
        turn = rng.uniform(-20.0, 20.0)
        trunk = [rng.uniform(-8.0, 8.0), lean, turn]
        neck = [0.0, rng.uniform(-20.0, 25.0), rng.uniform(-30.0, 30.0)]
        target = pose(r if "L" in which else None, r if "R" in which else None, trunk, neck)
        d_out, hold, d_back, pause = rng.uniform(0.7, 1.1), rng.uniform(0.2, 0.5), rng.uniform(0.5, 0.8), rng.uniform(0.2, 0.6)
        times += [tk, tk + d_out, tk + d_out + hold, tk + d_out + hold + d_back]
        keys += [base, target, target, base]
        bent = rng.uniform(60.0, 100.0)
        el_mid = [bent if "L" in which else rest["el"], bent if "R" in which else rest["el"]]
        el_end = [r["el"] if "L" in which else rest["el"], r["el"] if "R" in which else rest["el"]]
        el_times += [tk, tk + 0.45 * d_out, tk + d_out, tk + d_out + hold, tk + d_out + hold + 0.5 * d_back,
                     tk + d_out + hold + d_back]
        el_keys += [[rest["el"]] * 2, el_mid, el_end, el_end, el_mid, [rest["el"]] * 2]
        tk += d_out + hold + d_back + pause
    V = _minjerk_keys(t, np.array(times), np.array(keys))
    V[:, [3, 10]] = _minjerk_keys(t, np.array(el_times), np.array(el_keys))
    rv = np.zeros((F, _S, 3))
    for i, side in enumerate("LR"):
        o = 7 * i
        _put_ball(rv, side + "Shoulder", V[:, o:o + 3])
        _put_hinge(rv, side + "Elbow", -V[:, o + 3], _smooth(rng, t, 2, 0.1, 0.5, k=3) * 0.2 * slack)
        _put_ball(rv, side + "Wrist", V[:, o + 4:o + 7])
        # the legs stand still (the trunk leans at the lumbar joint)
        _put_ball(rv, side + "Hip", np.column_stack([np.full(F, 3.0), np.full(F, -5.0), np.zeros(F)])
                  + 0.5 * _smooth(rng, t, 3, 0.05, 0.3, k=3))
        _put_hinge(rv, side + "Knee", 6.0 + _smooth(rng, t, 1, 0.05, 0.3, k=3)[:, 0], np.zeros((F, 2)))
    _put_ball(rv, "Lumbar", V[:, 14:17])
    _put_ball(rv, "Neck", V[:, 17:20])
    root_pos, yaw = _standing_root(rng, t, subj)
    root_rot = _rot_z(yaw)
    return root_pos, root_rot, rv


def _kick(rng: np.random.Generator, t: np.ndarray, subj: _Subject, slack: np.ndarray):
    """Fighting guard with front and roundhouse kicks of either leg (fast: the foot reaches 6-10 m/s) and punches."""
    F, T = t.size, float(t[-1])
    # channels per leg: hip (x, y, z), knee; shared: lumbar (x, y, z)
    guard = [0.0, -15.0, 0.0, 20.0]
    times, keys = [0.0], [guard + guard + [0.0, 5.0, 0.0]]
    tk = rng.uniform(0.3, 0.7)
    while tk < T + 3.0:
        side = int(rng.integers(2))
        round_ = rng.uniform() < 0.4
        hi = rng.uniform(80.0, 100.0)
        if round_:
            chamber = [rng.uniform(40, 60), -rng.uniform(50, 70), rng.uniform(-30, -15), rng.uniform(110, 130)]
            extend = [rng.uniform(60, 75), -rng.uniform(55, 75), rng.uniform(-35, -20), rng.uniform(5, 15)]
            lean = [rng.uniform(15, 30), rng.uniform(0, 10), 0.0]  # away from the kicking (left) leg
        else:
            chamber = [rng.uniform(0, 10), -hi + 10.0, 0.0, rng.uniform(110, 130)]
            extend = [rng.uniform(0, 10), -hi, 0.0, rng.uniform(3, 12)]
            lean = [0.0, -rng.uniform(10, 20), 0.0]
        support = [0.0, -25.0, 0.0, 25.0]
        if side == 1:  # the right leg kicks: lateral lean the other way
            lean[0] = -lean[0]

        def row(kick, sup, trunk):
            legs = (kick + sup) if side == 0 else (sup + kick)
            return legs + trunk

        d_ch, d_ex, d_re, d_dn = rng.uniform(0.25, 0.35), rng.uniform(0.22, 0.3), rng.uniform(0.2, 0.25), rng.uniform(0.3, 0.4)
        times += [tk, tk + d_ch, tk + d_ch + d_ex, tk + d_ch + d_ex + 0.05, tk + d_ch + d_ex + 0.05 + d_re,
                  tk + d_ch + d_ex + 0.05 + d_re + d_dn]
        g_trunk = [0.0, 5.0, 0.0]
        keys += [row(guard, guard, g_trunk), row(chamber, support, [0.5 * x for x in lean]), row(extend, support, lean),
                 row(extend, support, lean), row(chamber, support, [0.5 * x for x in lean]), row(guard, guard, g_trunk)]
        tk = times[-1] + rng.uniform(0.6, 1.2)
    V = _minjerk_keys(t, np.array(times), np.array(keys))
    # arms: guard, with punches (shoulder forward, elbow straight) in between
    guard_arm = [20.0, -45.0, -20.0, 110.0]
    a_times, a_keys = [0.0], [guard_arm * 2]
    tp = rng.uniform(0.2, 0.8)
    while tp < T + 1.0:
        punch = [rng.uniform(0.0, 20.0), -rng.uniform(75.0, 95.0), rng.uniform(-10.0, 15.0), rng.uniform(5.0, 20.0)]
        row = punch + guard_arm if rng.uniform() < 0.5 else guard_arm + punch
        d_out, d_back = rng.uniform(0.15, 0.22), rng.uniform(0.2, 0.3)
        a_times += [tp, tp + d_out, tp + d_out + 0.04, tp + d_out + 0.04 + d_back]
        a_keys += [guard_arm * 2, row, row, guard_arm * 2]
        tp = a_times[-1] + rng.uniform(0.4, 1.2)
    A = _minjerk_keys(t, np.array(a_times), np.array(a_keys))
    rv = np.zeros((F, _S, 3))
    for i, side in enumerate("LR"):
        o = 4 * i
        var = _smooth(rng, t, 3, 0.1, 0.5, k=3)
        sl = _smooth(rng, t, 2, 0.1, 0.5, k=3) * 0.3 * slack
        _put_ball(rv, side + "Hip", V[:, o:o + 3] + var)
        _put_hinge(rv, side + "Knee", V[:, o + 3], sl)
        _put_ball(rv, side + "Ankle", np.column_stack([np.zeros(F), 0.25 * V[:, o + 3] - 5.0, np.zeros(F)]) + 0.5 * var)
        _put_ball(rv, side + "Shoulder", A[:, 4 * i:4 * i + 3] + 3.0 * var)
        _put_hinge(rv, side + "Elbow", -A[:, 4 * i + 3] + 8.0 * _smooth(rng, t, 1, 0.2, 0.8, k=3)[:, 0], sl)
        _put_ball(rv, side + "Wrist", 2.0 * var)
    _put_ball(rv, "Lumbar", V[:, 8:11])
    _put_ball(rv, "Neck", -0.6 * V[:, 8:11] + _smooth(rng, t, 3, 0.05, 0.3) * 2.0)
    root_pos, yaw = _standing_root(rng, t, subj)
    root_rot = _rot_z(yaw)
    return root_pos, root_rot, rv


def _motion(motion: str, rng, t, subj, slack):
    if motion in _GAITS:
        return _locomotion(motion, rng, t, subj, slack)
    if motion == "reach":
        return _reach(rng, t, subj, slack)
    if motion == "kick":
        return _kick(rng, t, subj, slack)
    return _rom_motion(rng, t, subj, slack)
