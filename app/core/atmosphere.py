"""Atmospheric correction of gravity anomalies (IAG / GRS80 convention).

Why
    The normal gravity field (GRS80 / WGS84, and through it ``γ`` of SPEC §1) is that of
    an ellipsoid whose mass ``GM`` *includes* the atmosphere.  A point at height ``h``
    is not attracted by the atmosphere above it (for spherical layering the shells above
    exert no net attraction), so observed gravity lacks ``G·M_atm(>h)/r²`` compared with
    normal gravity.  The IAG convention (Moritz 1980, *Geodetic Reference System 1980*;
    Hinze et al. 2005, *Geophysics* 70(4) J25–J32) therefore **adds** the correction
    ``δg_atm(h) > 0`` to the anomaly (equivalently, subtracts it from normal gravity):

        ``Δg = g_obs − γ + δg_atm``   and, with SPEC §1,   ``z_atm = z + δg_atm(h)``

    i.e. the free-air disturbance at flight height corrected for the atmosphere is
    ``dg + atmospheric_correction_mgal(h)``.  0.87 mGal at sea level, 0.84 at 330 m,
    0.60 at 3 km, 0.23 at 10 km.

Models
    ``"iag"`` (default): ``δg_atm(h) = G·M(>h)/(R+h)²`` with
    ``M(>h) = 4π ∫_h^∞ ρ(z) (R+z)² dz`` the mass of a spherically layered U.S. Standard
    Atmosphere 1976 (NOAA-S/T 76-1562; layers to 84.852 km geopotential altitude) above
    the point, ``R`` = 6 371 008.8 m (GRS80 mean radius).  This is the definition behind
    the IAG/GRS80 table; it is evaluated once on a 5 m grid from −5 km to 86 km by the
    trapezoidal rule and interpolated linearly (interpolation error < 1e-6 mGal).
    Valid for −5 km ≤ h ≤ 86 km (0 above 86 km, where the atmosphere's attraction is below
    1e-5 mGal).

    ``"wenzel"``: the quadratic of Wenzel (1985) adopted by Hinze et al. (2005) for the
    North American gravity database, ``δg_atm = 0.874 − 9.9e-5 h + 3.56e-9 h²`` mGal
    (h in m).  It is a fit to the IAG values for land heights: within 0.007 mGal of
    ``"iag"`` from 0 to 8.5 km, 0.012 mGal high at 10 km, and wrong beyond ~14 km (its
    minimum is at 13.9 km).  Valid for −1 km ≤ h ≤ 10 km.

Height
    ``h`` is the height above sea level (orthometric).  Ellipsoidal heights may be used
    instead: a geoid undulation of N metres changes the correction by ≈ 1e-4·N mGal
    (0.003 mGal for 30 m), far below airborne noise.

Checks (tests/core/test_atmosphere.py): the ``"iag"`` values against an independent
integration of the same standard atmosphere from its pressure law (≤ 1e-3 mGal), against
the Wenzel quadratic (≤ 0.012 mGal over 0–10 km) and against the fifth-degree polynomial
fit to the IAG table used in Geoscience Australia's gravity processing
(``0.871 − 1.0298e-4 h + 5.3105e-9 h² − 2.1642e-13 h³ + 9.5246e-18 h⁴ − 2.2411e-22 h⁵``,
≤ 0.003 mGal over 0–10 km).  The printed GRS80 table itself (Moritz 1980) could not be
retrieved here; its values rounded to 0.01 mGal are what these fits reproduce.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

#: Newtonian constant of gravitation (CODATA 2018), m³ kg⁻¹ s⁻².
G_SI = 6.67430e-11
#: GRS80 mean radius R1 = (2a + b)/3 (m), the radius of the spherical layering.
R_MEAN_M = 6371008.7714
#: U.S. Standard Atmosphere 1976: effective Earth radius for geopotential altitude (m),
#: g0, molar mass of air, gas constant (its value), layer bases (geopotential m),
#: lapse rates (K/m), sea-level temperature (K) and pressure (Pa).
_USSA_R0_M = 6356766.0
_USSA_G0 = 9.80665
_USSA_M = 28.9644e-3
_USSA_RSTAR = 8.31432
_USSA_HB = np.array([0.0, 11000.0, 20000.0, 32000.0, 47000.0, 51000.0, 71000.0, 84852.0])
_USSA_L = np.array([-6.5, 0.0, 1.0, 2.8, 0.0, -2.8, -2.0]) / 1000.0
_USSA_T0 = 288.15
_USSA_P0 = 101325.0

IAG_VALID_M = (-5000.0, 86000.0)
WENZEL_VALID_M = (-1000.0, 10000.0)


def _ussa76_bases():
    """Temperature and pressure at the base of each USSA76 layer."""
    tb, pb = [_USSA_T0], [_USSA_P0]
    k = _USSA_G0 * _USSA_M / _USSA_RSTAR
    for i in range(len(_USSA_L)):
        dh = _USSA_HB[i + 1] - _USSA_HB[i]
        t1 = tb[i] + _USSA_L[i] * dh
        if _USSA_L[i] == 0.0:
            p1 = pb[i] * np.exp(-k * dh / tb[i])
        else:
            p1 = pb[i] * (tb[i] / t1) ** (k / _USSA_L[i])
        tb.append(t1)
        pb.append(p1)
    return np.array(tb), np.array(pb)


def ussa76_temperature_pressure(z_m):
    """Temperature (K) and pressure (Pa) of the U.S. Standard Atmosphere 1976 at geometric
    altitude ``z_m`` (m, −5 km … 86 km; the first layer extended below sea level)."""
    z = np.asarray(z_m, dtype=float)
    hgp = _USSA_R0_M * z / (_USSA_R0_M + z)            # geopotential altitude
    tb, pb = _ussa76_bases()
    i = np.clip(np.searchsorted(_USSA_HB, hgp, side="right") - 1, 0, len(_USSA_L) - 1)
    lap = _USSA_L[i]
    t = tb[i] + lap * (hgp - _USSA_HB[i])
    k = _USSA_G0 * _USSA_M / _USSA_RSTAR
    iso = lap == 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        p_grad = pb[i] * (tb[i] / t) ** (k / np.where(iso, 1.0, lap))
    p_iso = pb[i] * np.exp(-k * (hgp - _USSA_HB[i]) / tb[i])
    return t, np.where(iso, p_iso, p_grad)


def ussa76_density_kgm3(z_m):
    """Air density (kg/m³) of the U.S. Standard Atmosphere 1976 at geometric altitude (m)."""
    t, p = ussa76_temperature_pressure(z_m)
    return p * _USSA_M / (_USSA_RSTAR * t)


@lru_cache(maxsize=1)
def _iag_table(step_m: float = 5.0):
    z = np.arange(IAG_VALID_M[0], IAG_VALID_M[1] + step_m, step_m)
    f = ussa76_density_kgm3(z) * (R_MEAN_M + z) ** 2
    # mass above each node: cumulative trapezoid from the top
    seg = 0.5 * (f[1:] + f[:-1]) * np.diff(z)
    above = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
    dg = G_SI * 4.0 * np.pi * above / (R_MEAN_M + z) ** 2 * 1e5
    return z, dg


def atmospheric_correction_mgal(h_m, model: str = "iag"):
    """Atmospheric correction δg_atm (mGal, positive), to be **added** to the anomaly.

    ``dg_corrected = dg + atmospheric_correction_mgal(h)`` (module docstring: the normal
    field's mass includes the atmosphere above the point, which does not attract it).

    Parameters
    ----------
    h_m : array_like
        Height above sea level (m); ellipsoidal heights are acceptable (≈ 1e-4 mGal per
        metre of geoid undulation).  NaN propagates.
    model : {"iag", "wenzel"}
        ``"iag"``: attraction of the U.S. Standard Atmosphere 1976 above the point
        (spherical layering), valid −5 … 86 km (0 above).  ``"wenzel"``: Wenzel (1985) /
        Hinze et al. (2005) quadratic ``0.874 − 9.9e-5 h + 3.56e-9 h²``, valid −1 … 10 km.

    Returns
    -------
    ndarray (or float for scalar input)
        δg_atm in mGal, same shape as ``h_m``.

    Raises
    ------
    ValueError
        Unknown model, or a finite height outside the model's validity range.
    """
    h = np.asarray(h_m, dtype=float)
    if model == "iag":
        lo, hi = IAG_VALID_M[0], np.inf
    elif model == "wenzel":
        lo, hi = WENZEL_VALID_M
    else:
        raise ValueError(f"unknown atmospheric correction model {model!r} (expected 'iag' or 'wenzel')")
    fin = np.isfinite(h)
    if np.any(fin & ((h < lo) | (h > hi))):
        bad = h[fin & ((h < lo) | (h > hi))]
        raise ValueError(f"height {float(bad.flat[0]):.1f} m outside the validity range of the "
                         f"{model!r} atmospheric correction ({lo:g} … {hi:g} m)")
    if model == "wenzel":
        out = 0.874 - 9.9e-5 * h + 3.56e-9 * h * h
    else:
        z, dg = _iag_table()
        out = np.interp(h, z, dg, right=0.0)
        out = np.where(fin, out, np.nan)
    return out if out.ndim else float(out)
