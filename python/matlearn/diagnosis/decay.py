"""Modal decay evidence: does the recorded motion die out as fast as the nominal damping says?

Why a separate test. Rayleigh damping C = alpha_M M + alpha_K K is diagonal in the undamped modes
of *any* mesh: a mode of angular frequency w decays at sigma(w) = (alpha_M + alpha_K w^2) / 2,
and backward Euler at the scene's step h adds its own numerical decay (`step_rates`, exact for a
linear mode). The decay at a *measured* frequency is therefore a property of the damping law and
the integrator alone. A stiffness scale, a density, a softer region, a compliant clamp or the
coarse mesh's discretisation error move the frequencies and the mode shapes, never sigma(w) at a
given w. The marker-residual tests (pipeline.py) cannot say the same: a coarse mesh errs most in
the high-frequency content that damping removes, so on a coarse model a damping change hides
below the discretisation floor (docs/results.md, sessions 16 and 21: independent seeds 11-13's
Rayleigh L-brackets and strain-dependent plates, `[]` with held-out gaps of 5-16 %).

Estimate, per train recording without drive points (a free motion: a release, a pluck, a sag):
the seen markers' trajectories (T, 3K) reduced to their leading SVD components; poles from the
eigensystem realisation algorithm (Hankel matrix of the components) as the start; then the
dominant two damped oscillations plus a constant fitted to all components by variable projection
(the poles nonlinear, every component's amplitudes linear; scipy least_squares), with the decay's
standard error from the Jacobian. The dominant oscillation (largest amplitude) is used when it
is seen for at least one period, lies below half the Nyquist frequency and is lightly damped on
the nominal model (sigma / w <= MAX_DAMPING_RATIO: an overdamped motion has no decay rate to
time). Its measured decay is divided by the nominal law's at the measured frequency (the
frequency backward Euler would give that decay with: `predicted_decay`).

Decision. The log-ratios of the usable recordings are averaged with inverse-variance weights. A
damping change is concluded when the mean ratio lies outside DECAY_BAND and beyond MIN_Z
standard errors of 1. The band is the estimator's spread where the damping is right: over the
development and independent suites (122 cases, bench/results/decay_scan.json, docs/results.md
session 23) every case without a damping change lies in 0.69-1.26 (amplitude-dependent stiffness
biases it low, density and a damaged body high), every damping change detected in 1.55-4.09 (five
strain-dependent truths, whose extra damping is small at small strains, stay in band).

What it cannot tell: Rayleigh from strain-dependent damping (one amplitude per recording), nor
reliably how the change splits between alpha_M (a mass term decays every mode alike) and alpha_K
(a stiffness term as w^2) when the recordings show one frequency. `evidence` offers candidate
coefficients that all reproduce the measured decays (the nominal ones scaled together, alpha_M
alone moved, alpha_K alone moved, and both fitted where the usable oscillations span
frequencies SPREAD apart); the diagnosis picks one by the train markers."""
from __future__ import annotations

import numpy as np

from ..materials import Damping

DECAY_BAND = (0.5, 1.5)
MIN_Z = 4.0
MAX_DAMPING_RATIO = 0.3
MIN_PERIODS = 1.0
COMPONENTS = 6
MODES = 2
SPREAD = 1.25  # frequency ratio over which the measured decays separate alpha_M from alpha_K


def step_rates(k, c, h):
    """(angular frequency, decay rate) (1/s) of backward Euler at step h on the mode
    x'' + c x' + k x = 0: the eigenvalues z of its step, w = |arg z| / h, sigma = -ln|z| / h."""
    D = 1.0 + h * c + h * h * k
    z = np.roots([1.0, -(2.0 + h * c) / D, 1.0 / D])[0]
    return abs(float(np.angle(z))) / h, -float(np.log(abs(z))) / h


def predicted_decay(w, damping: Damping, h: float) -> float:
    """Decay rate (1/s) the model's damping law and backward Euler give the mode that they make
    oscillate at angular frequency w: the mode's stiffness k is found on the underdamped branch
    (where the step's frequency grows with k); inf when no mode of this law oscillates at w
    (damped too heavily)."""
    aM, aK = float(damping.alpha_mass), float(damping.alpha_stiffness)

    def freq(k):
        return step_rates(k, aM + aK * k, h)[0]

    ks = w * w * np.geomspace(1e-2, 16.0, 240)
    prev_k, prev_w = 0.0, 0.0
    for k in ks:
        wk = freq(k)
        if wk >= w:
            break
        if wk < prev_w:  # past the branch's peak frequency
            return float("inf")
        prev_k, prev_w = k, wk
    else:
        return float("inf")
    lo, hi = prev_k, k
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if freq(mid) < w:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * hi:
            break
    k = 0.5 * (lo + hi)
    return step_rates(k, aM + aK * k, h)[1]


def _uniform_tracks(rec):
    """(t from 0, (T, m) coordinates of the markers seen in at least 90 % of the frames, gaps
    filled linearly, on a uniform time grid) or None."""
    t = np.asarray(rec.times, float)
    X = np.asarray(rec.markers, float)
    seen = np.all(np.isfinite(X), axis=2)
    keep = seen.mean(axis=0) >= 0.9
    if keep.sum() < 1 or len(t) < 12:
        return None
    X = X[:, keep]
    tu = np.linspace(t[0], t[-1], len(t))
    cols = []
    for k in range(X.shape[1]):
        ok = np.all(np.isfinite(X[:, k]), axis=1)
        for d in range(3):
            cols.append(np.interp(tu, t[ok], X[ok, k, d]))
    return tu - tu[0], np.stack(cols, axis=1)


def _components(Y, p=COMPONENTS):
    Y = Y - Y[-1]
    U, S, _ = np.linalg.svd(Y, full_matrices=False)
    p = min(p, len(S))
    return U[:, :p] * S[:p]


def _era_poles(Y, dt, order):
    """Continuous-time poles of an order-`order` realisation of the signals Y (T, p)."""
    N = len(Y)
    L = N // 2
    H = np.concatenate([Y[i:i + N - L].T for i in range(L)], axis=0)
    U, S, Vt = np.linalg.svd(H[:, :-1], full_matrices=False)
    n = min(order, int(np.sum(S > S[0] * 1e-10)))
    Si = 1.0 / np.sqrt(S[:n])
    A = (Si[:, None] * U[:, :n].T) @ H[:, 1:] @ (Vt[:n].T * Si[None, :])
    z = np.linalg.eigvals(A).astype(complex)
    z = z[np.abs(z) > 1e-12]
    lam = np.log(z) / dt
    Z = z[None, :] ** np.arange(N)[:, None]
    C = np.linalg.lstsq(Z, Y.astype(complex), rcond=None)[0]
    amp = np.linalg.norm(C, axis=1) * np.sqrt(np.mean(np.abs(Z) ** 2, axis=0))
    return lam, amp


def _basis(t, poles):
    cols = [np.ones_like(t)]
    for s, w in poles:
        e = np.exp(-s * t)
        cols += [e * np.cos(w * t), e * np.sin(w * t)]
    return np.stack(cols, axis=1)


def _varpro(t, Y, poles0):
    """Damped oscillations (sigma, w) shared by every column of Y plus a constant, fitted by
    variable projection. Returns (poles (M, 2), their standard errors (M, 2), amplitudes (M,),
    relative residual)."""
    from scipy.optimize import least_squares

    def res(x):
        B = _basis(t, x.reshape(-1, 2))
        return (Y - B @ np.linalg.lstsq(B, Y, rcond=None)[0]).ravel()

    x0 = np.asarray(poles0, float).ravel()
    sol = least_squares(res, x0, method="lm", x_scale="jac")
    poles = sol.x.reshape(-1, 2)
    dof = max(sol.fun.size - x0.size - Y.shape[1] * (1 + 2 * len(poles)), 1)
    s2 = float(sol.fun @ sol.fun) / dof
    JtJ = sol.jac.T @ sol.jac
    try:
        se = np.sqrt(np.maximum(np.diag(np.linalg.inv(JtJ)), 0.0) * s2).reshape(-1, 2)
    except np.linalg.LinAlgError:
        se = np.full_like(poles, np.inf)
    B = _basis(t, poles)
    C = np.linalg.lstsq(B, Y, rcond=None)[0]
    amps = np.array([np.linalg.norm(B[:, 1 + 2 * k:3 + 2 * k] @ C[1 + 2 * k:3 + 2 * k]) for k in range(len(poles))])
    rel = float(np.linalg.norm(sol.fun) / max(np.linalg.norm(Y - Y.mean(axis=0)), 1e-300))
    return poles, se, amps, rel


def recording_decay(rec, damping: Damping, h: float) -> dict | None:
    """The dominant oscillation of one free recording: {w, sigma, sigma_se, predicted, ratio,
    log_se, rel} (1/s), or None where the recording cannot time a decay (drive points, too few
    frames or markers, no lightly damped oscillation seen for a period)."""
    if rec.has_drive or rec.markers is None:
        return None
    got = _uniform_tracks(rec)
    if got is None:
        return None
    t, X = got
    Y = _components(X)
    dt = t[1] - t[0]
    T, nyquist = t[-1], np.pi / dt
    lam, amp = _era_poles(Y, dt, 2 * MODES + 4)
    cand = sorted(((a, l) for a, l in zip(amp, lam)
                   if 2 * np.pi * MIN_PERIODS / T < l.imag < 0.5 * nyquist and -l.real > 0),
                  key=lambda x: -x[0])
    if not cand:
        return None
    try:
        poles, se, amps, rel = _varpro(t, Y, [(-l.real, l.imag) for _, l in cand[:MODES]])
    except (np.linalg.LinAlgError, ValueError):
        return None
    def timed(j):
        """(sigma, w, se, nominal-law decay) of fitted oscillation j, or None where its decay
        cannot be timed: seen for less than MIN_PERIODS, near the Nyquist frequency, growing, or
        damped too heavily on the nominal law."""
        s, w = (float(v) for v in poles[j])
        if not (w * T >= 2 * np.pi * MIN_PERIODS and w < 0.5 * nyquist and s > 0 and np.isfinite(se[j, 0])):
            return None
        pred = predicted_decay(w, damping, h)
        return (s, w, float(se[j, 0]), pred) if 0 < pred <= MAX_DAMPING_RATIO * w else None

    got = [timed(j) for j in range(len(poles))]
    # every well-timed oscillation (the coefficient fit); the dominant one (the ratio)
    modes = [{"w": g[1], "sigma": g[0], "log_se": g[2] / g[0]} for g in got if g and g[2] < 0.3 * g[0]]
    k = int(np.argmax(amps))
    if got[k] is None:
        return None
    sigma, w, sigma_se, pred = got[k]
    return {"w": w, "sigma": sigma, "sigma_se": sigma_se, "predicted": pred,
            "ratio": sigma / pred, "log_se": sigma_se / sigma, "rel": rel,
            "share": float(amps[k] / amps.sum()), "modes": modes}


def _weights(rows) -> np.ndarray:
    """Inverse variances of the rows' log decay rates (their relative errors floored at 0.1 %)."""
    return np.array([1.0 / max(r["log_se"], 1e-3) ** 2 for r in rows])


def _log_misfits(rows, damping: Damping, h: float) -> np.ndarray:
    """log(measured / predicted decay) of each row under `damping` at step h (inf where the law
    makes no mode oscillate at the row's frequency)."""
    with np.errstate(divide="ignore"):
        return np.array([np.log(r["sigma"] / predicted_decay(r["w"], damping, h)) for r in rows])


def _matched(rows, start, direction, h):
    """The Rayleigh coefficients start + t direction (t as far as both stay >= 0, up to a 1e3-fold
    change) whose predicted decays match the measured ones of `rows` (inverse-variance weighted
    log-mean ratio 1), by bisection: the decays grow with t."""
    start, direction = np.asarray(start, float), np.asarray(direction, float)
    wts = _weights(rows)

    def coefficients(t):
        return np.maximum(start + t * direction, 0.0)

    def misfit(t):
        return float(wts @ _log_misfits(rows, Damping(*coefficients(t)), h))

    neg = [-start[i] / direction[i] for i in range(2) if direction[i] > 0]
    lo = max(neg) if neg else 0.0
    hi = 1e3 * max(float(np.max(np.abs(start / np.where(direction > 0, direction, np.inf)))), 1.0)
    if misfit(hi) > 0:
        return tuple(coefficients(hi))
    if misfit(lo) < 0:
        return tuple(coefficients(lo))
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if misfit(mid) > 0:
            lo = mid
        else:
            hi = mid
    return tuple(float(v) for v in coefficients(0.5 * (lo + hi)))


def _two_coefficients(modes, start, h):
    """(alpha_M, alpha_K) >= 0 whose predicted decays match the measured ones of `modes`
    (weighted least squares in the log-ratio, from `start`), or None when the modes do not span
    frequencies far enough apart (max / min < SPREAD) to separate the two."""
    from scipy.optimize import least_squares

    ws = np.array([m["w"] for m in modes])
    if len(modes) < 2 or ws.max() < SPREAD * ws.min():
        return None
    sig = np.array([m["sigma"] for m in modes])
    # each mode's relative error floored at 1 %: no single well-timed mode dictates the split
    wts = 1.0 / np.maximum([m["log_se"] for m in modes], 1e-2)
    scale = np.array([max(start[0], 1e-3), max(start[1], 1e-7)])

    def res(x):
        d = Damping(*(x * scale))
        pred = np.array([predicted_decay(w, d, h) for w in ws])
        return wts * np.log(sig / np.minimum(pred, 1e6 * sig))

    sol = least_squares(res, np.array(start) / scale, bounds=(0.0, np.inf), method="trf")
    return tuple(float(v) for v in sol.x * scale)


def evidence(problem) -> dict:
    """Decay evidence of the problem's train recordings: {"recordings": [per-recording dict or
    None], "ratio": weighted mean measured / predicted decay (None without a usable recording),
    "z": its distance from 1 in standard errors, "change": "higher" / "lower" / None, "scale":
    the common factor of the nominal coefficients matching the measured decays, "alpha_mass",
    "alpha_stiffness": the estimate (the "scaled" candidate until `choose`), "split": its
    candidate's name, "candidates": {name: (alpha_M, alpha_K)} each matching the measured
    decays (module docstring)}."""
    scene = problem.scene
    rows = []
    for rec in problem.train:
        try:
            rows.append(recording_decay(rec, scene.damping, scene.time_step))
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            rows.append(None)
    good = [r for r in rows if r is not None]
    out = {"recordings": rows, "ratio": None, "z": None, "change": None, "scale": None,
           "band": list(DECAY_BAND), "min_z": MIN_Z}
    if not good:
        return out
    wts = _weights(good)
    m = float(wts @ np.log([r["ratio"] for r in good]) / wts.sum())
    se = float(1.0 / np.sqrt(wts.sum()))
    ratio, z = float(np.exp(m)), m / se
    change = None
    if abs(z) >= MIN_Z and ratio > DECAY_BAND[1]:
        change = "higher"
    elif abs(z) >= MIN_Z and ratio < DECAY_BAND[0]:
        change = "lower"
    aM, aK = float(scene.damping.alpha_mass), float(scene.damping.alpha_stiffness)
    h = scene.time_step
    # candidate coefficients matching the measured decays: the nominal ones scaled together,
    # only alpha_M moved, only alpha_K moved, and both fitted where the oscillations span
    # frequencies SPREAD apart; which one is used is decided on the train markers
    # (pipeline._decay_claim). Directions are in units that make a unit step move the decay at
    # the measured frequencies by about the same amount.
    w_ref = float(np.median([r["w"] for r in good]))
    base = (aM, aK) if aM > 0 or aK > 0 else (1.0, 0.0)  # alpha_M alone when both are zero
    cands = {"scaled": _matched(good, (0.0, 0.0), base, h),
             "mass": _matched(good, (aM, aK), (1.0, 0.0), h),
             "stiffness": _matched(good, (aM, aK), (0.0, 1.0 / w_ref**2), h)}
    try:
        two = _two_coefficients([m for r in good for m in r["modes"]], cands["scaled"], h)
    except (ValueError, np.linalg.LinAlgError):  # a non-finite start (a mode no law of the family decays like)
        two = None
    if two is not None:
        cands["fitted"] = two
    c = cands["scaled"][0] / base[0] if base[0] > 0 else cands["scaled"][1] / base[1]
    out.update(ratio=ratio, z=float(z), change=change, scale=float(c), candidates=cands,
               alpha_mass=cands["scaled"][0], alpha_stiffness=cands["scaled"][1], split="scaled")
    return out


def rayleigh_theta(ctx, coefficients) -> list:
    """The rayleigh_damping family's parameters (effects.damping_of units) of the Rayleigh
    coefficients (alpha_M, alpha_K)."""
    d = ctx.damping
    return [(coefficients[0] - float(d.alpha_mass)) / (0.1 * ctx.omega),
            (coefficients[1] - float(d.alpha_stiffness)) * ctx.omega / 0.1]


def choose(ev: dict, name: str) -> dict:
    """The evidence with candidate `name`'s coefficients as its estimate."""
    a, k = ev["candidates"][name]
    return dict(ev, alpha_mass=float(a), alpha_stiffness=float(k), split=name)


def explained(ev: dict, h: float) -> float:
    """The share of the decay mismatch that the estimate's coefficients remove at step h: 1 -
    the inverse-variance weighted sum of squared log(measured / predicted decay) over the usable
    recordings with the estimate (alpha_mass, alpha_stiffness), divided by the same with the
    nominal law (in [0, 1]; 0 without a usable recording or a mismatch). This is what a damping
    effect claimed from the decays (pipeline._decay_claim) "explains" (formats.md `explained`):
    its marker-residual share is blind to the change (module docstring)."""
    good = [r for r in ev["recordings"] if r is not None]
    if not good or ev.get("alpha_mass") is None:
        return 0.0
    wts = _weights(good)
    before = float(wts @ np.log([r["ratio"] for r in good]) ** 2)
    after = float(wts @ _log_misfits(good, Damping(ev["alpha_mass"], ev["alpha_stiffness"]), h) ** 2)
    if not (before > 0 and np.isfinite(after)):
        return 0.0
    return float(np.clip(1.0 - after / before, 0.0, 1.0))


def summary(ev: dict) -> str:
    """One progress line."""
    if ev["ratio"] is None:
        return "decay: no train recording times a decay (drive points, or no lightly damped oscillation seen)"
    per = ", ".join("-" if r is None else f"{r['ratio']:.2f} at {r['w']:.0f} rad/s" for r in ev["recordings"])
    return (f"decay: measured / nominal-law decay x{ev['ratio']:.2f} ({ev['z']:.1f} standard errors; per "
            f"recording {per}); damping change: {ev['change'] or 'none'} (band {ev['band']})")


def report(ev: dict) -> dict:
    """The evidence for diagnosis.json: the mean ratio, its z, the change concluded, and per
    train recording the dominant oscillation (null where none is usable)."""
    names = {"w": "angular_frequency", "sigma": "decay_rate", "sigma_se": "decay_rate_se",
             "predicted": "nominal_decay_rate", "ratio": "ratio"}
    return {"ratio": ev["ratio"], "z": ev["z"], "change": ev["change"], "band": ev["band"],
            "alpha_mass": ev.get("alpha_mass"), "alpha_stiffness": ev.get("alpha_stiffness"),
            "coefficients": ev.get("split"),
            "recordings": [None if r is None else {names[k]: r[k] for k in names} for r in ev["recordings"]]}
