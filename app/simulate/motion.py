"""Aircraft motion: flight plan, horizontal trajectory, vertical motion.

Horizontal motion is a piecewise polynomial in time in the projected plane
(metres, relative to the survey centre): straight segments at constant speed on
lines (level, unaccelerated), quintic Hermite transitions (turns, transits) that
match position, velocity and zero acceleration at both ends, so the horizontal
acceleration is continuous.

Vertical motion is an acceleration ``a_up(t)`` defined as the not-a-knot cubic
spline through samples on a fine uniform grid (≥100 Hz) of a band-limited random
process (phugoid + coloured turbulence).  Velocity and height are its exact
antiderivatives (``scipy.interpolate.PPoly``), so for any interval
``(V(b) − V(a))/(b − a)`` is exactly the mean of ``a_up`` over ``(a, b]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.fft import next_fast_len
from scipy.interpolate import CubicSpline, PPoly


@dataclass
class PlannedLine:
    """One survey line in the plane (km relative to the survey centre)."""

    line: str
    kind: str              # main | tie | repeat
    track: str | None
    start_km: tuple[float, float]   # (east, north) where the line window starts
    end_km: tuple[float, float]


def layout_lines(cfg) -> list[PlannedLine]:
    """Main, tie and repeat lines in flying order (headings alternate).

    Returns
    -------
    list of PlannedLine
        Main lines (east–west, south to north), then tie lines (north–south,
        west to east), then the repeat track flown ``cfg.n_repeat`` times.
    """
    out: list[PlannedLine] = []
    L = cfg.main_length_km
    ys = (np.arange(cfg.n_main) - (cfg.n_main - 1) / 2.0) * cfg.main_spacing_km
    for i, y in enumerate(ys):
        xa, xb = (-L / 2, L / 2) if i % 2 == 0 else (L / 2, -L / 2)
        out.append(PlannedLine(f"M{i + 1:03d}", "main", None, (xa, float(y)), (xb, float(y))))
    if cfg.n_tie > 0:
        y_lo = float(ys.min()) - cfg.tie_margin_km
        y_hi = float(ys.max()) + cfg.tie_margin_km
        xs = (np.arange(cfg.n_tie) + 0.5) / cfg.n_tie * L - L / 2
        for j, x in enumerate(xs):
            ya, yb = (y_lo, y_hi) if j % 2 == 0 else (y_hi, y_lo)
            out.append(PlannedLine(f"T{j + 1:02d}", "tie", None, (float(x), ya), (float(x), yb)))
    if cfg.n_repeat > 0:
        Lr = cfg.repeat_length_km or L
        # midway between the two central main lines
        y = 0.0 if cfg.n_main % 2 == 0 else 0.5 * cfg.main_spacing_km
        alternate = getattr(cfg, "repeat_alternate", False)
        for r in range(cfg.n_repeat):   # same direction (racetrack) or alternating (reversal turns)
            xa, xb = (-Lr / 2, Lr / 2) if not (alternate and r % 2 == 1) else (Lr / 2, -Lr / 2)
            out.append(PlannedLine(f"R1-{r + 1}", "repeat", "R1", (xa, y), (xb, y)))
    return out


def _quintic(p0, v0, p1, v1, T):
    """Coefficients (highest power first) of the quintic with p(0)=p0, p'(0)=v0,
    p''(0)=0, p(T)=p1, p'(T)=v1, p''(T)=0 in local time s ∈ [0, T]."""
    M = np.array([[T ** 3, T ** 4, T ** 5],
                  [3 * T ** 2, 4 * T ** 3, 5 * T ** 4],
                  [6 * T, 12 * T ** 2, 20 * T ** 3]])
    rhs = np.array([p1 - p0 - v0 * T, v1 - v0, 0.0])
    c3, c4, c5 = np.linalg.solve(M, rhs)
    return np.array([c5, c4, c3, 0.0, v0, p0])


def _turn(a, b, r):
    """Displacement (m) and angle (rad) of a circular turn of radius r from heading a to b.

    Left turn when ``a × b ≥ 0`` (exact reversals turn left):
    ``Y − X = ±r·(rot90(a) − rot90(b))``.
    """
    cross = a[0] * b[1] - a[1] * b[0]
    sgn = 1.0 if cross >= 0 else -1.0
    th = float(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0)))
    rot = lambda u: np.array([-u[1], u[0]])  # noqa: E731
    return sgn * r * (rot(a) - rot(b)), th


@dataclass
class FlightPath:
    """Horizontal trajectory of one flight and the line windows it contains."""

    name: str
    t0: float
    t1: float
    x_pp: PPoly            # easting relative to centre (m) as a function of time
    y_pp: PPoly            # northing relative to centre (m)
    windows: list[tuple[PlannedLine, float, float]]


def gnss_quantum_s(cfg) -> float:
    """Time quantum of the flight plan: 0.1 s when that is a whole number of GNSS periods (10, 20,
    50 Hz: the original behaviour), else one GNSS period (2 Hz: 0.5 s, 1 Hz: 1 s, 5 Hz: 0.2 s)."""
    rate = float(cfg.gnss_rate_hz)
    r = 0.1 * rate
    return 0.1 if abs(r - round(r)) < 1e-9 and round(r) >= 1 else 1.0 / rate


def _quantizer(cfg):
    q = gnss_quantum_s(cfg)
    if q == 0.1:
        return lambda v: round(v, 1)
    return lambda v: round(round(v / q) * q, 6)


class _PathBuilder:
    """Horizontal trajectory built segment by segment: ``x(t)``, ``y(t)`` piecewise polynomials
    (metres), every segment end quantised by ``rq`` (the plan's time quantum)."""

    def __init__(self, t0: float, rq):
        self.rq = rq
        self.t = t0
        self.breaks = [t0]
        self.cx: list[np.ndarray] = []
        self.cy: list[np.ndarray] = []

    def _advance(self, T: float) -> None:
        self.t = self.rq(self.t + T)
        self.breaks.append(self.t)

    def straight(self, p, v, T: float) -> None:
        """Constant velocity ``v`` (m/s) from ``p`` (m) for ``T`` s."""
        self.cx.append(np.array([0, 0, 0, 0, v[0], p[0]], dtype=float))
        self.cy.append(np.array([0, 0, 0, 0, v[1], p[1]], dtype=float))
        self._advance(T)

    def quintic(self, a, va, b, vb, T: float) -> None:
        """Quintic Hermite transition from (``a``, ``va``) to (``b``, ``vb``) in ``T`` s, zero
        acceleration at both ends."""
        self.cx.append(_quintic(a[0], va[0], b[0], vb[0], T))
        self.cy.append(_quintic(a[1], va[1], b[1], vb[1], T))
        self._advance(T)

    def polys(self) -> tuple[PPoly, PPoly]:
        """``(x_pp, y_pp)`` of the segments so far."""
        return (PPoly(np.array(self.cx).T, np.array(self.breaks)),
                PPoly(np.array(self.cy).T, np.array(self.breaks)))


def _reversal(path: _PathBuilder, P, vp, s0, vv, T: float) -> None:
    """Reverse onto the same track: straight on, a U-turn to the left (diameter 2r,
    r = v·T/π) and an S-curve back onto the track over 7.5 r, ending at ``s0`` with ``vv``."""
    rq = path.rq
    up_ = vp / np.hypot(*vp)
    sp = float(np.hypot(*vp))
    r = sp * T / np.pi
    nrm = np.array([-up_[1], up_[0]])
    Ls = 7.5 * r
    along = max(float(np.dot(s0 - P, up_)), 0.0)
    T0 = rq((along + Ls) / sp)
    A = P + vp * T0
    B = A + nrm * 2.0 * r
    Tsc = rq(float(np.dot(B - s0, up_)) / float(np.hypot(*vv)))
    path.straight(P, vp, T0)
    path.quintic(A, vp, B, vv, T)
    path.quintic(B, vv, s0, vv, Tsc)


def _transit(path: _PathBuilder, P, vp, s0, vv, T: float, v: float) -> None:
    """Fly from ``P`` (velocity ``vp``) to a distant line start ``s0`` (velocity ``vv``).

    A circular-like turn towards the target, straight at cruise speed ``v``, a turn onto the
    line (reversals become racetrack turns of radius r = v·T/π); a target too close for
    turn–straight–turn gets one smooth transition.
    """
    rq = path.rq
    dist = float(np.hypot(*(s0 - P)))
    r = v * T / np.pi
    up = vp / np.hypot(*vp)
    un = vv / np.hypot(*vv)
    ut = (s0 - P) / dist
    for _ in range(4):
        D1, th1 = _turn(up, ut, r)
        D2, th2 = _turn(ut, un, r)
        W1, W2 = P + D1, s0 - D2
        ut_new = (W2 - W1) / max(float(np.hypot(*(W2 - W1))), 1e-9)
        if np.allclose(ut_new, ut, atol=1e-9):
            break
        ut = ut_new
    Ls = float(np.dot(W2 - W1, ut))
    if Ls < 500.0:
        # target too close for a turn–straight–turn: one smooth transition
        path.quintic(P, vp, s0, vv, rq(max(T, dist / v * 1.3 + 30.0)))
        return
    Ts = rq(Ls / v)
    vt = (W2 - W1) / Ts
    pieces = []
    if th1 > 0.05:
        pieces.append(("q", P, vp, W1, vt, rq(max(r * th1 / v, 5.0))))
    else:
        W1 = P
        Ts = rq(float(np.hypot(*(W2 - W1))) / v)
        vt = (W2 - W1) / Ts
    pieces.append(("s", W1, vt, None, None, Ts))
    if th2 > 0.05:
        pieces.append(("q", W2, vt, s0, vv, rq(max(r * th2 / v, 5.0))))
    else:   # no final turn: stretch the straight to s0
        pieces[-1] = ("s", W1, (s0 - W1) / Ts, None, None, Ts)
    for kind_, A, va, B, vb, TT in pieces:
        if kind_ == "q":
            path.quintic(A, va, B, vb, TT)
        else:
            path.straight(A, va, TT)


def _transition(path: _PathBuilder, prev_end, s0, vv, T: float, cfg) -> None:
    """From the end of the previous line ``prev_end = (x, y, vx, vy)`` to the next line's
    straight segment start ``s0`` (velocity ``vv``) in nominal turn time ``T``: a reversal
    onto the same track, a turn onto a neighbouring line, or a transit."""
    px, py, pvx, pvy = prev_end
    P = np.array([px, py])
    vp = np.array([pvx, pvy])
    dist = float(np.hypot(*(s0 - P)))
    up_ = vp / np.hypot(*vp)
    un_ = vv / np.hypot(*vv)
    lateral = float(up_[0] * (s0 - P)[1] - up_[1] * (s0 - P)[0])
    if float(np.dot(up_, un_)) < -0.99 and abs(lateral) < 100.0:
        _reversal(path, P, vp, s0, vv, T)
    elif dist <= 2.5 * cfg.main_spacing_km * 1000.0 + 1.0:
        path.quintic(P, vp, s0, vv, T)     # turn onto a neighbouring line: one smooth transition
    else:
        _transit(path, P, vp, s0, vv, T, cfg.speed_ms)


def plan_flight(name: str, lines: list[PlannedLine], t0: float, cfg, rng) -> FlightPath:
    """Build the horizontal trajectory of one flight flying ``lines`` in order.

    All segment durations are multiples of the plan's time quantum (0.1 s at 10 Hz GNSS, one GNSS
    period at 1, 2 or 5 Hz), so line windows start and end on GNSS epochs (``t0`` is a whole second).
    With ``cfg.wind_ms`` the ground speed on a line is ``speed_ms + wind_ms·(east component of the
    heading)`` (a wind blowing towards the east).  A pass that reverses onto the same track
    (alternating repeat passes) is reached by a reversal: straight on, a U-turn to the left
    (diameter 2r, r = v·T/π) and an S-curve back onto the track over 7.5 r.

    Parameters
    ----------
    name : str
        Flight name.
    lines : list of PlannedLine
        The lines in flying order.
    t0 : float
        Start time (s).
    cfg : SimConfig
    rng : numpy.random.Generator
        One turn time per transition between lines (``cfg.turn_s``).

    Returns
    -------
    FlightPath
    """
    rq = _quantizer(cfg)
    v = cfg.speed_ms
    wind = float(getattr(cfg, "wind_ms", 0.0))
    path = _PathBuilder(t0, rq)
    windows = []
    prev_end = None  # (x, y, vx, vy)
    for k, ln in enumerate(lines):
        a = np.array(ln.start_km) * 1000.0
        b = np.array(ln.end_km) * 1000.0
        d = b - a
        length = float(np.hypot(*d))
        u = d / length
        v_line = v + wind * float(u[0]) if wind != 0.0 else v
        dur = rq(length / v_line)
        vv = u * (length / dur)                 # exact speed so the window is a whole number of quanta
        pre = cfg.run_in_s + (cfg.lead_s if k == 0 else 0.0)
        post = cfg.run_out_s + (cfg.tail_s if k == len(lines) - 1 else 0.0)
        s0 = a - vv * pre                       # start of the straight segment
        if prev_end is not None:
            T = rq(float(rng.uniform(*cfg.turn_s)))
            _transition(path, prev_end, s0, vv, T, cfg)
        seg_T = rq(pre + dur + post)
        windows.append((ln, rq(path.t + pre), rq(path.t + pre + dur)))
        path.straight(s0, vv, seg_T)
        prev_end = (s0[0] + vv[0] * seg_T, s0[1] + vv[1] * seg_T, vv[0], vv[1])
    x_pp, y_pp = path.polys()
    return FlightPath(name, t0, path.t, x_pp, y_pp, windows)


def _band_noise(n: int, fs: float, gain_fn, rng) -> np.ndarray:
    """Real Gaussian noise of length n at rate fs with amplitude response gain_fn(f)."""
    w = rng.standard_normal(n)
    W = np.fft.rfft(w)
    f = np.fft.rfftfreq(n, 1.0 / fs)
    x = np.fft.irfft(W * gain_fn(f), n)
    return x


def vertical_motion(t0: float, t1: float, cfg, rng):
    """Vertical acceleration of one flight as an exact piecewise cubic.

    Parameters
    ----------
    t0, t1 : float
        Flight time span (s).
    cfg : SimConfig
    rng : numpy.random.Generator

    Returns
    -------
    a_pp, v_pp, h_pp : PPoly
        Vertical acceleration (m/s², up), velocity (m/s) and height offset (m)
        about the nominal flight height; ``v_pp`` and ``h_pp`` are exact
        antiderivatives of ``a_pp`` (``v`` shifted to zero mean).
    info : dict
        Realised RMS of the turbulence acceleration and phugoid period.
    """
    fs = cfg.fine_rate_hz
    pad = 20.0
    n = next_fast_len(int(np.ceil((t1 - t0 + 2 * pad) * fs)) + 1, real=True)   # fast FFT size
    tf = t0 - pad + np.arange(n) / fs
    f_lo, f_hi = cfg.turbulence_band_hz
    fmax = cfg.motion_max_hz

    if getattr(cfg, "turbulence_spectrum", "band") == "peaked":
        # PSD ∝ x^α / (1 + x^(α+β)), x = f / f_peak: rises as f^α, falls as f^−β (real aircraft:
        # most power 0.1–0.5 Hz)
        fpk = cfg.turbulence_peak_hz
        al, be = cfg.turbulence_slopes

        def turb_gain(f):
            x = f / fpk
            g = np.sqrt(x ** al / (1.0 + x ** (al + be)))
            return np.where(f < fmax, g, 0.0)
    elif getattr(cfg, "turbulence_spectrum", "band") == "band":
        def turb_gain(f):
            g = (f / f_lo) ** 2 / (1.0 + (f / f_lo) ** 2) / (1.0 + (f / f_hi) ** 4)
            return np.where(f < fmax, g, 0.0)
    else:
        raise ValueError(f"unknown turbulence_spectrum {cfg.turbulence_spectrum!r}")

    turb = _band_noise(n, fs, turb_gain, rng)
    turb /= max(np.std(turb), 1e-300)
    # slowly varying intensity (correlation ~10 min), per-flight level drawn in the range
    lvl_lo, lvl_hi = cfg.turbulence_rms_ms2
    env = _band_noise(n, fs, lambda f: np.exp(-(f * 600.0) ** 2), rng)
    env = env / max(np.std(env), 1e-300)
    env = np.exp(getattr(cfg, "turbulence_envelope_log_std", 0.5) * env)
    env = env / np.mean(env) * rng.uniform(lvl_lo, lvl_hi)
    a = turb * env
    # phugoid: narrow band around 1/T_p with height amplitude ~ phugoid_amp_m
    Tp = float(rng.uniform(*cfg.phugoid_period_s))
    fp = 1.0 / Tp
    ph = _band_noise(n, fs, lambda f: np.exp(-0.5 * ((f - fp) / (0.08 * fp)) ** 2), rng)
    ph = ph / max(np.std(ph), 1e-300) * cfg.phugoid_amp_m * (2 * np.pi * fp) ** 2 / np.sqrt(2.0)
    a = a + ph
    # band-limit the sum (the envelope spreads the spectrum a little)
    A = np.fft.rfft(a)
    f = np.fft.rfftfreq(n, 1.0 / fs)
    A[f > fmax * 1.25] = 0.0
    A[f < 1.0 / 2000.0] = 0.0
    a = np.fft.irfft(A, n)
    a_pp = CubicSpline(tf, a, bc_type="not-a-knot")
    a_pp = PPoly(a_pp.c, a_pp.x)
    v_pp = a_pp.antiderivative()
    # zero-mean velocity (an integration constant), then height offset about zero mean
    vbar = float(np.mean(v_pp(tf)))
    v_pp.c[-1] -= vbar
    h_pp = v_pp.antiderivative()
    hbar = float(np.mean(h_pp(tf)))
    h_pp.c[-1] -= hbar
    info = {"turbulence_rms_ms2": float(np.std(turb * env)), "phugoid_period_s": Tp,
            "a_rms_ms2": float(np.std(a))}
    return a_pp, v_pp, h_pp, info


@dataclass
class Drape:
    """Draped flight surface: height above the nominal flight height (m) as a smooth function of
    position, a sum of plane waves (random directions, wavelengths uniform in a range, random
    phases) plus a constant, scaled and shifted so that on the planned line windows it spans
    exactly ``[−amp, +amp]`` (the flight height is ``height_m ± amp`` there).  Repeat passes over
    a track therefore fly the same profile (terrain following)."""

    kx: np.ndarray         # rad/m, per component
    ky: np.ndarray
    phase: np.ndarray
    amp: np.ndarray        # m, per component
    offset: float = 0.0    # m

    def __call__(self, x_m, y_m) -> np.ndarray:
        x = np.asarray(x_m, dtype=float)[..., None]
        y = np.asarray(y_m, dtype=float)[..., None]
        return np.sum(self.amp * np.cos(self.kx * x + self.ky * y + self.phase), axis=-1) + self.offset

    def info(self) -> dict:
        return {"wavelength_km": (2 * np.pi / np.hypot(self.kx, self.ky) / 1000.0).tolist(),
                "direction_deg": np.rad2deg(np.arctan2(self.kx, self.ky)).tolist(),
                "phase_rad": self.phase.tolist(), "amplitude_m": self.amp.tolist(),
                "offset_m": self.offset,
                "formula": "sum(amplitude_m*cos(kx*x + ky*y + phase_rad)) + offset_m, k = 2*pi/wavelength, "
                           "(kx, ky) = k*(sin, cos)(direction_deg), x, y metres east/north of the survey centre"}


def make_drape(cfg, lines: list[PlannedLine], rng) -> Drape:
    """The drape surface of ``cfg`` (``drape_amp_m``, ``drape_wavelength_km``, ``drape_components``)."""
    n = int(cfg.drape_components)
    lam = rng.uniform(*cfg.drape_wavelength_km, n) * 1000.0
    th = rng.uniform(0.0, np.pi, n)
    ph = rng.uniform(0.0, 2 * np.pi, n)
    k = 2 * np.pi / lam
    dr = Drape(k * np.sin(th), k * np.cos(th), ph, np.ones(n))
    pts = []
    for ln in lines:
        a, b = np.array(ln.start_km) * 1000.0, np.array(ln.end_km) * 1000.0
        m = max(2, int(np.hypot(*(b - a)) / 50.0) + 1)
        s = np.linspace(0.0, 1.0, m)[:, None]
        pts.append(a + s * (b - a))
    P = np.concatenate(pts)
    v = dr(P[:, 0], P[:, 1])
    half = 0.5 * float(v.max() - v.min())
    scale = cfg.drape_amp_m / half
    dr.amp = np.full(n, scale)
    dr.offset = -0.5 * float(v.max() + v.min()) * scale
    return dr
