"""Geodesy for airborne gravimetry: normal gravity, Eötvös, radii, projections.

All functions are pure and vectorised over numpy arrays.  Latitudes and
longitudes in degrees, heights in metres (ellipsoidal), velocities in m/s,
gravity values in mGal (1 mGal = 1e-5 m/s²).
"""

from __future__ import annotations

import re

import numpy as np

#: Earth rotation rate (rad/s), GRS80/WGS84.
OMEGA_EARTH = 7.292115e-5
#: WGS84 semi-major axis (m) and first eccentricity squared.
WGS84_A_M = 6378137.0
WGS84_E2 = 6.69437999014e-3
MGAL_PER_MS2 = 1e5


def normal_gravity_helmert_mgal(lat_deg, h_m):
    """Helmert 1901 normal gravity at height, as in seed 001 (mGal).

    ``γ = 9.7803·(1 + 0.005302 sin²φ − 0.000007 sin²2φ) − 0.00014 − 2·0.00123²·h`` m/s².

    Parameters
    ----------
    lat_deg : array_like
        Geodetic latitude (degrees).
    h_m : array_like
        Height above the ellipsoid (m), same shape (or broadcastable).

    Returns
    -------
    ndarray
        Normal gravity in mGal, broadcast shape of the inputs.
    """
    phi = np.deg2rad(np.asarray(lat_deg, dtype=float))
    h = np.asarray(h_m, dtype=float)
    g_ms2 = (9.7803 * (1.0 + 0.005302 * np.sin(phi) ** 2 - 0.000007 * np.sin(2.0 * phi) ** 2)
             - 0.00014 - 2.0 * 0.00123 ** 2 * h)
    return g_ms2 * MGAL_PER_MS2


def normal_gravity_wgs84_mgal(lat_deg, h_m):
    """WGS84 normal gravity at height: Somigliana closed form through ``boule`` (mGal).

    Parameters
    ----------
    lat_deg, h_m : array_like
        Geodetic latitude (degrees) and ellipsoidal height (m).

    Returns
    -------
    ndarray
        Normal gravity (mGal), the magnitude of the normal gravity vector.
    """
    import boule

    return _somigliana_mgal(boule.WGS84, lat_deg, h_m)


def normal_gravity_grs80_mgal(lat_deg, h_m):
    """GRS80 normal gravity at height (Moritz 1980: γ_e = 978 032.677 mGal), through ``boule``
    (mGal); 0.14 mGal above WGS84's everywhere (γ_e 978 032.677 against 978 032.534: the same
    ellipsoid to 0.1 mm, GM and ω slightly different) — for surveys whose contractor states GRS80."""
    import boule

    return _somigliana_mgal(boule.GRS80, lat_deg, h_m)


def _somigliana_mgal(ellipsoid, lat_deg, h_m):
    lat = np.asarray(lat_deg, dtype=float)
    h = np.asarray(h_m, dtype=float)
    lat, h = np.broadcast_arrays(lat, h)
    lon = np.zeros_like(lat)
    return np.asarray(ellipsoid.normal_gravity((lon, lat, h)), dtype=float)


def normal_gravity_mgal(lat_deg, h_m, model: str = "WGS84"):
    """Normal gravity (mGal) by the model the survey chose: ``"WGS84"``, ``"GRS80"`` or
    ``"Helmert1901"``."""
    if model == "WGS84":
        return normal_gravity_wgs84_mgal(lat_deg, h_m)
    if model == "GRS80":
        return normal_gravity_grs80_mgal(lat_deg, h_m)
    if model == "Helmert1901":
        return normal_gravity_helmert_mgal(lat_deg, h_m)
    raise ValueError(f"unknown normal gravity model {model!r} (expected 'WGS84', 'GRS80' or 'Helmert1901')")


def radii_of_curvature_m(lat_deg, a_m: float = WGS84_A_M, e2: float = WGS84_E2):
    """Meridian and prime-vertical radii of curvature of the ellipsoid (m).

    Returns
    -------
    (R_M, R_N) : tuple of ndarray
        ``R_M = a(1−e²)/(1−e² sin²φ)^{3/2}``, ``R_N = a/(1−e² sin²φ)^{1/2}``.
    """
    s2 = np.sin(np.deg2rad(np.asarray(lat_deg, dtype=float))) ** 2
    w = 1.0 - e2 * s2
    return a_m * (1.0 - e2) / w ** 1.5, a_m / np.sqrt(w)


def step_lengths_km(lat_deg, lon_deg, h_m=None) -> np.ndarray:
    """Length of each step between consecutive positions, on the WGS84 ellipsoid (km).

    Each step uses the radii of curvature at the mid-latitude (and mid-height):
    ``ds² = ((R_M+h)·Δφ)² + ((R_N+h)·cos φ·Δλ)²`` — exact to second order for
    the short steps of 1–20 Hz GNSS.  A longitude step across ±180° is taken the
    short way.

    Returns
    -------
    ndarray, shape (n − 1,)
        Empty with fewer than two positions.
    """
    lat = np.asarray(lat_deg, dtype=float)
    lon = np.asarray(lon_deg, dtype=float)
    if lat.shape != lon.shape:
        raise ValueError("lat_deg and lon_deg must have the same shape")
    if lat.size < 2:
        return np.zeros(0)
    h = np.zeros_like(lat) if h_m is None else np.asarray(h_m, dtype=float)
    phi = np.deg2rad(lat)
    lam = np.unwrap(np.deg2rad(lon))
    phim = 0.5 * (phi[1:] + phi[:-1])
    hm = 0.5 * (h[1:] + h[:-1])
    r_m, r_n = radii_of_curvature_m(np.rad2deg(phim))
    dn = (r_m + hm) * np.diff(phi)
    de = (r_n + hm) * np.cos(phim) * np.diff(lam)
    return np.hypot(dn, de) / 1000.0


def path_length_km(lat_deg, lon_deg, h_m=None) -> float:
    """Length of a track through consecutive positions, on the WGS84 ellipsoid (km): the sum of
    :func:`step_lengths_km`."""
    return float(np.sum(step_lengths_km(lat_deg, lon_deg, h_m)))


def eotvos_mgal(lat_deg, h_m, ve_ms, vn_ms):
    """Eötvös correction (Harlan 1968, leading terms with the ellipsoid radii), mGal.

    ``E = 2Ω v_E cos φ + v_E²/(R_N+h) + v_N²/(R_M+h)``; positive when flying east.
    Added to the measurement (SPEC §1): ``z = f̄ − V̇ − γ + E``.

    Parameters
    ----------
    lat_deg, h_m : array_like
        Latitude (degrees), ellipsoidal height (m).
    ve_ms, vn_ms : array_like
        East and north ground velocity (m/s).
    """
    lat = np.asarray(lat_deg, dtype=float)
    h = np.asarray(h_m, dtype=float)
    ve = np.asarray(ve_ms, dtype=float)
    vn = np.asarray(vn_ms, dtype=float)
    r_m, r_n = radii_of_curvature_m(lat)
    e_ms2 = (2.0 * OMEGA_EARTH * ve * np.cos(np.deg2rad(lat))
             + ve ** 2 / (r_n + h) + vn ** 2 / (r_m + h))
    return e_ms2 * MGAL_PER_MS2


def velocities_from_positions_ms(t_s, lat_deg, lon_deg, h_m):
    """East and north velocity (m/s) from positions by central differences.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Strictly increasing times (s).
    lat_deg, lon_deg, h_m : ndarray, shape (n,)

    Returns
    -------
    (ve_ms, vn_ms) : tuple of ndarray, shape (n,)
    """
    t = np.asarray(t_s, dtype=float)
    lat = np.asarray(lat_deg, dtype=float)
    lon = np.asarray(lon_deg, dtype=float)
    h = np.asarray(h_m, dtype=float)
    if t.size < 2:
        return np.zeros_like(t), np.zeros_like(t)
    r_m, r_n = radii_of_curvature_m(lat)
    phi = np.deg2rad(lat)
    dlat = np.gradient(np.deg2rad(lat), t)
    dlon = np.gradient(np.unwrap(np.deg2rad(lon)), t)
    return dlon * (r_n + h) * np.cos(phi), dlat * (r_m + h)


def horizontal_velocity_misfit_ms(t_s, lat_deg, lon_deg, h_m, ve_ms, vn_ms,
                                  min_speed_ms: float = 20.0) -> tuple[float, float, int]:
    """How far a GNSS file's horizontal velocities are from the velocity of its positions.

    The two are the same motion and agree to a few cm/s on real records; a disagreement of
    the order of the speed says a column is mislabelled — latitude and longitude swapped
    (both valid numbers), east and north swapped, a sign flipped — and normal gravity and the
    Eötvös correction, which use them, are then wrong by hundreds of mGal.

    Parameters
    ----------
    t_s, lat_deg, lon_deg, h_m, ve_ms, vn_ms : ndarray, shape (n,)
        One flight's GNSS record (s, degrees, m, m/s).
    min_speed_ms : float
        Only epochs moving at least this fast (by either velocity) are compared (m/s).

    Returns
    -------
    (float, float, int)
        Median speed (m/s), median magnitude of the vector difference (m/s), and the
        number of epochs compared (NaNs when none).
    """
    ve_p, vn_p = velocities_from_positions_ms(t_s, lat_deg, lon_deg, h_m)
    ve = np.asarray(ve_ms, dtype=float)
    vn = np.asarray(vn_ms, dtype=float)
    speed = np.maximum(np.hypot(ve, vn), np.hypot(ve_p, vn_p))
    use = np.isfinite(speed) & (speed >= min_speed_ms) & np.isfinite(ve_p) & np.isfinite(vn_p)
    if not use.any():
        return float("nan"), float("nan"), 0
    diff = np.hypot(ve - ve_p, vn - vn_p)[use]
    return float(np.median(speed[use])), float(np.median(diff)), int(use.sum())


def heading_departures(t_s, ve_ms, vn_ms, max_deg: float = 30.0, min_speed_ms: float = 5.0) -> dict:
    """Where a survey line's track leaves the line's own heading (a turn inside its window).

    The line's heading is that of the sum of the unit velocity vectors of its moving epochs
    (the direction it is mostly flown in); an epoch departs when its heading (from ``ve``,
    ``vn``) differs from it by more than ``max_deg``.  A straight line flown through turbulence
    departs by a few degrees; a procedure turn at a line end by up to 180°.

    Parameters
    ----------
    t_s, ve_ms, vn_ms : ndarray, shape (n,)
        The line's epochs (s) and horizontal velocity (m/s, east and north).
    max_deg : float
        Departure (degrees) beyond which an epoch is off the line's heading.
    min_speed_ms : float
        Epochs slower than this (m/s) have no heading and are ignored.

    Returns
    -------
    dict
        ``seconds``: total duration (s) of the departing epochs (each counts its GNSS step);
        ``max_deg``: the largest departure (degrees, 0–180); ``first_s``, ``last_s``: the first
        and last departing epoch times (NaN when none).
    """
    t = np.asarray(t_s, dtype=float)
    ve = np.asarray(ve_ms, dtype=float)
    vn = np.asarray(vn_ms, dtype=float)
    speed = np.hypot(ve, vn)
    moving = np.isfinite(speed) & (speed >= min_speed_ms)
    none = {"seconds": 0.0, "max_deg": 0.0, "first_s": float("nan"), "last_s": float("nan")}
    if moving.sum() < 2:
        return none
    ue, un = ve[moving] / speed[moving], vn[moving] / speed[moving]
    mean_heading = np.arctan2(ue.sum(), un.sum())
    dev = np.abs(np.rad2deg(np.angle(np.exp(1j * (np.arctan2(ue, un) - mean_heading)))))
    off = dev > max_deg
    if not off.any():
        return {**none, "max_deg": float(dev.max())}
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    tm = t[moving][off]
    return {"seconds": float(off.sum() * step), "max_deg": float(dev.max()), "first_s": float(tm[0]),
            "last_s": float(tm[-1])}


#: the relabellings of a GNSS file's (ve, vn) tried by :func:`velocity_relabelling`: (label, (a, b)) with the
#: new ve = sign_a · column a, the new vn = sign_b · column b (columns 0 = file's ve, 1 = file's vn)
RELABELLINGS = (("ve and vn swapped", ((1, 1), (0, 1))), ("ve negated", ((0, -1), (1, 1))),
                ("vn negated", ((0, 1), (1, -1))), ("ve and vn negated", ((0, -1), (1, -1))),
                ("ve and vn swapped and negated", ((1, -1), (0, -1))),
                ("ve and vn swapped, the new ve negated", ((1, -1), (0, 1))),
                ("ve and vn swapped, the new vn negated", ((1, 1), (0, -1))))


def velocity_relabelling(t_s, lat_deg, lon_deg, h_m, ve_ms, vn_ms, min_speed_ms: float = 20.0):
    """Which relabelling of a GNSS file's horizontal velocities (:data:`RELABELLINGS`) matches the
    velocity of its positions best.

    Each candidate is scored by the mean magnitude of its vector difference from the positions'
    velocity (:func:`velocities_from_positions_ms`) over the epochs moving faster than
    ``min_speed_ms``: a mean, not a median, so that the turns decide between candidates that lines
    flown due east (vn ≈ 0) cannot tell apart.

    Parameters
    ----------
    t_s, lat_deg, lon_deg, h_m, ve_ms, vn_ms : ndarray, shape (n,)
        One flight's GNSS record (s, degrees, m, m/s).

    Returns
    -------
    (str, ndarray, ndarray, float, float) or None
        Label, the relabelled ve and vn (m/s), the best candidate's mean misfit and the runner-up's
        (m/s); None when fewer than 10 epochs move.
    """
    ve_p, vn_p = velocities_from_positions_ms(t_s, lat_deg, lon_deg, h_m)
    cols = (np.asarray(ve_ms, dtype=float), np.asarray(vn_ms, dtype=float))
    use = (np.hypot(ve_p, vn_p) >= min_speed_ms) & np.isfinite(ve_p) & np.isfinite(vn_p)
    use &= np.isfinite(cols[0]) & np.isfinite(cols[1])
    if use.sum() < 10:
        return None
    scored = []
    for label, ((ia, sa), (ib, sb)) in RELABELLINGS:
        ve, vn = sa * cols[ia], sb * cols[ib]
        scored.append((float(np.mean(np.hypot(ve - ve_p, vn - vn_p)[use])), label, ve, vn))
    scored.sort(key=lambda x: x[0])
    (best, label, ve, vn), runner_up = scored[0], scored[1][0]
    return label, ve, vn, best, runner_up


def vertical_velocity_from_heights_ms(t_s, h_m):
    """Vertical velocity (m/s, up) of one contiguous GNSS run from its heights alone.

    ``V(t_k) = s'(t_k)`` where ``s`` is the not-a-knot cubic spline through
    ``(t_k, h_k)``.  The measurement (SPEC §1) uses ``(V_k − V_{k−1})/Δt``; for
    the spline that difference is ``∫ s''(t) dt / Δt`` over ``(t_{k−1}, t_k]``,
    i.e. exactly the mean vertical acceleration of the interpolated trajectory
    over the GNSS interval — the quantity the interval-mean gravimeter reading
    ``f̄_k`` is compared with.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Strictly increasing times (s) of one run without record gaps, n ≥ 4.
    h_m : ndarray, shape (n,)
        Ellipsoidal heights (m).

    Returns
    -------
    ndarray, shape (n,)
        ``V`` (m/s).

    Raises
    ------
    ValueError
        Fewer than 4 samples (the not-a-knot spline needs 4).
    """
    from scipy.interpolate import CubicSpline

    t = np.asarray(t_s, dtype=float)
    h = np.asarray(h_m, dtype=float)
    if t.size < 4:
        raise ValueError(f"a not-a-knot cubic spline needs at least 4 samples, got {t.size}")
    x = t - t[0]  # GPS seconds since the epoch are ~1e9: keep the abscissae small
    return CubicSpline(x, h, bc_type="not-a-knot")(x, 1)


def mean_position_deg(lon_deg, lat_deg) -> tuple[float, float]:
    """Mean longitude and latitude of points (degrees): the longitudes averaged on the circle
    (the direction of the mean unit vector), so points across the antimeridian or written
    from 0 to 360° average where they lie; NaN ignored."""
    lon_r = np.deg2rad(np.asarray(lon_deg, dtype=float))
    lon = float(np.rad2deg(np.arctan2(np.nanmean(np.sin(lon_r)), np.nanmean(np.cos(lon_r)))))
    return lon, float(np.nanmean(lat_deg))


def utm_crs_for(lon_deg, lat_deg) -> str:
    """EPSG code of the UTM zone containing the mean of the given points.

    The longitudes are averaged on the circle (the direction of the mean unit vector), so a
    survey across the antimeridian (179.8°…−179.9°) or across 0° written from 0 to 360°
    (359.6°…0.2°) gets the zone it lies in, not one half the world away.
    """
    lon, lat = mean_position_deg(lon_deg, lat_deg)
    zone = int(np.floor((lon + 180.0) / 6.0)) % 60 + 1
    return f"EPSG:{32600 + zone if lat >= 0 else 32700 + zone}"


_UTM_WORDS = re.compile(r"(?i)\s*(?:wgs\s*84\s*/?\s*)?utm\s*(?:zone\s*)?(\d{1,2})\s*([ns])\w*\s*")


def epsg_for_text(crs: str, max_chars: int = 20_000) -> int | None:
    """The EPSG code a CRS written some other way stands for, when that is clear: a UTM zone
    in words (``UTM 57N``, ``utm zone 7 s``: WGS 84's zone, 326zz/327zz), or a CRS PROJ reads
    and identifies (a WKT; at most ``max_chars`` characters are given to PROJ).  None otherwise."""
    m = _UTM_WORDS.fullmatch(crs)
    if m and 1 <= int(m.group(1)) <= 60:
        return (32600 if m.group(2).lower() == "n" else 32700) + int(m.group(1))
    if len(crs) > max_chars:
        return None
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        return CRS.from_user_input(crs).to_epsg(min_confidence=90)
    except CRSError:
        return None


def crs_fault(crs: str) -> str | None:
    """Why ``crs`` cannot hold a survey (None when it can): unknown to PROJ, not projected
    (distances and the grid need linear units), axes in another unit than the metre, or a projection that parses and still fails on
    every point (``+k=1e-10``) or shrinks distances absurdly — 0.01° of latitude at the centre of
    its area of use (0°, 0° without one) must come out within 10× of 1113 m."""
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError

    try:
        c = CRS.from_user_input(crs)
    except CRSError as e:
        code = epsg_for_text(crs)
        if code is not None:   # a UTM zone in words PROJ does not read ('UTM 57N')
            return f"{crs!r} is not a CRS PROJ reads: for WGS 84's UTM zone write crs = 'EPSG:{code}'"
        return f"unknown CRS: {str(e)[:200]}"
    if not c.is_projected:
        return (f"{c.name} is not a projected CRS: distances and the grid need one in linear units "
                "(e.g. a UTM zone, EPSG:326xx)")
    name = c.name if c.name and c.name != "unknown" else "the CRS"
    units = {a.unit_name for a in c.axis_info[:2]}
    if not units <= {"metre", "meter"}:
        # every distance downstream (easting_km, line lengths, ρ, the grid) is the coordinate in
        # metres / 1000: a CRS in km or feet passed the check below (its unit converted) and then
        # put the survey 1000× or 0.3048× its size on the map, silently
        return (f"{name} has its axes in {', '.join(sorted(units))}: the coordinates are taken in metres "
                "(distances, the grid); use the same projection in metres (e.g. +units=m, or the UTM zone's "
                "EPSG:326xx/327xx)")
    aou = c.area_of_use
    lon, lat = ((aou.west + aou.east) / 2.0, (aou.south + aou.north) / 2.0) if aou is not None else (0.0, 0.0)
    try:
        x, y = Transformer.from_crs("EPSG:4326", c, always_xy=True).transform([lon, lon], [lat, lat + 0.01])
    except Exception as e:  # noqa: BLE001 - PROJ's errors have no common base worth naming
        return f"{name} cannot be used: projecting a point fails ({str(e)[:150]})"
    d_m = float(np.hypot(x[1] - x[0], y[1] - y[0])) * c.axis_info[0].unit_conversion_factor
    if not (np.isfinite(d_m) and 0.1 * 1113.2 < d_m < 10.0 * 1113.2):
        return f"{name} cannot be used: 0.01° of latitude comes out as {d_m:.3g} m (1113 m expected)"
    return None


def scale_error(lon_deg, lat_deg, crs: str) -> float:
    """Relative error of distances in ``crs`` at a point (dimensionless): the projected length
    of 0.01° of latitude and of longitude there over their geodesic length on WGS84, the one
    farther from 1, minus 1.  On the equator: −0.0004 at a UTM zone's centre, 0.001 at its
    edge, 0.022 two zones away, 0.24 six (at 62° N six zones away: 0.04).

    Parameters
    ----------
    lon_deg, lat_deg : float
        The point (degrees).
    crs : str
        A projected CRS.
    """
    from pyproj import Geod, Transformer

    lon, lat = float(lon_deg), float(lat_deg)
    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    geod = Geod(ellps="WGS84")
    worst = 0.0
    for dlon, dlat in ((0.0, 0.01), (0.01, 0.0)):
        x, y = tr.transform([lon, lon + dlon], [lat, lat + dlat])
        _, _, d = geod.inv(lon, lat, lon + dlon, lat + dlat)
        k = float(np.hypot(x[1] - x[0], y[1] - y[0]) / d) - 1.0 if d > 0 else 0.0
        if np.isfinite(k) and abs(k) > abs(worst):
            worst = k
    return worst


def project_km(lon_deg, lat_deg, crs: str):
    """Project geographic coordinates to a projected CRS, in km.

    Returns
    -------
    (easting_km, northing_km) : tuple of ndarray
    """
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    x, y = tr.transform(np.asarray(lon_deg, dtype=float), np.asarray(lat_deg, dtype=float))
    return np.asarray(x) / 1000.0, np.asarray(y) / 1000.0


def unproject_km(easting_km, northing_km, crs: str):
    """Inverse of :func:`project_km`: (lon_deg, lat_deg)."""
    from pyproj import Transformer

    tr = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(np.asarray(easting_km, dtype=float) * 1000.0,
                            np.asarray(northing_km, dtype=float) * 1000.0)
    return np.asarray(lon), np.asarray(lat)
