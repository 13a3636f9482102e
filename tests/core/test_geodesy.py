"""Normal gravity and Eötvös against independent references (boule, hand formulas)."""

import math

import boule
import numpy as np
import pytest

from app.core import geodesy


def test_wgs84_equals_boule_and_textbook_constants():
    lat = np.array([-89.9, -60.0, -12.5, 0.0, 33.3, 65.5, 89.9])
    h = np.array([0.0, 500.0, 3000.0, 0.0, 1200.0, 3000.0, 100.0])
    ours = geodesy.normal_gravity_mgal(lat, h, "WGS84")
    ref = np.array([boule.WGS84.normal_gravity((0.0, la, hh)) for la, hh in zip(lat, h)])
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-6)
    # WGS84 defining values: equatorial and polar normal gravity on the ellipsoid
    assert geodesy.normal_gravity_mgal(0.0, 0.0) == pytest.approx(978032.53359, abs=1e-4)
    assert geodesy.normal_gravity_mgal(90.0, 0.0) == pytest.approx(983218.49378, abs=1e-4)
    # free-air gradient ≈ 0.3086 mGal/m
    grad = (geodesy.normal_gravity_mgal(45.0, 0.0) - geodesy.normal_gravity_mgal(45.0, 1000.0)) / 1000.0
    assert grad == pytest.approx(0.3086, abs=0.001)


@pytest.mark.parametrize("lat,h", [(0.0, 0.0), (30.0, 1000.0), (45.0, 3000.0), (65.5, 3100.0), (-30.75, 2500.0), (90.0, 0.0)])
def test_helmert_by_hand(lat, h):
    phi = math.radians(lat)
    hand = (9.7803 * (1 + 0.005302 * math.sin(phi) ** 2 - 0.000007 * math.sin(2 * phi) ** 2)
            - 0.00014 - 2 * 0.00123 ** 2 * h) * 1e5
    assert geodesy.normal_gravity_mgal(lat, h, "Helmert1901") == pytest.approx(hand, abs=1e-9)


def test_helmert_close_to_wgs84_at_sea_level():
    # The two models differ by the Potsdam correction (~14 mGal) and small terms.
    d = geodesy.normal_gravity_mgal(45.0, 0.0, "Helmert1901") - geodesy.normal_gravity_mgal(45.0, 0.0)
    assert -30 < d < 10


def test_unknown_model_rejected():
    with pytest.raises(ValueError, match="Helmert1901"):
        geodesy.normal_gravity_mgal(0.0, 0.0, "GRS67")


def _radii(lat):
    a, e2 = 6378137.0, 6.69437999014e-3
    s2 = math.sin(math.radians(lat)) ** 2
    return a * (1 - e2) / (1 - e2 * s2) ** 1.5, a / math.sqrt(1 - e2 * s2)


@pytest.mark.parametrize("lat", [0.0, 45.0, 65.5, -30.75])
def test_eotvos_steady_flights_closed_form(lat):
    v, h, om = 100.0, 3000.0, 7.292115e-5
    rm, rn = _radii(lat)
    east = 2 * om * v * math.cos(math.radians(lat)) + v * v / (rn + h)
    west = -2 * om * v * math.cos(math.radians(lat)) + v * v / (rn + h)
    north = v * v / (rm + h)
    assert geodesy.eotvos_mgal(lat, h, v, 0.0) == pytest.approx(east * 1e5, rel=1e-12)
    assert geodesy.eotvos_mgal(lat, h, -v, 0.0) == pytest.approx(west * 1e5, rel=1e-12)
    assert geodesy.eotvos_mgal(lat, h, 0.0, v) == pytest.approx(north * 1e5, rel=1e-12)
    assert geodesy.eotvos_mgal(lat, h, 0.0, -v) == pytest.approx(north * 1e5, rel=1e-12)


def test_eotvos_classic_knots_formula():
    # Classic marine form: E = 7.503 V cosφ sinα + 0.004154 V² (V in knots, mGal)
    lat, v = 60.0, 100.0
    kn = v / 0.514444
    classic = 7.503 * kn * math.cos(math.radians(lat)) + 0.004154 * kn ** 2
    assert geodesy.eotvos_mgal(lat, 0.0, v, 0.0) == pytest.approx(classic, rel=5e-3)


def test_velocities_from_positions():
    t = np.arange(0, 100, 0.1)
    lat0, lon0 = 65.5, 160.0
    rm, rn = _radii(lat0)
    ve, vn = 80.0, -60.0
    lat = lat0 + np.degrees(vn * t / (rm + 3000.0))
    lon = lon0 + np.degrees(ve * t / ((rn + 3000.0) * math.cos(math.radians(lat0))))
    e, n = geodesy.velocities_from_positions_ms(t, lat, lon, np.full_like(t, 3000.0))
    np.testing.assert_allclose(n, vn, rtol=1e-3)
    # the test track uses cos(lat0) for the longitude rate; lat drifts 0.05° → 0.2 % in v_E
    np.testing.assert_allclose(e, ve, rtol=3e-3)


def test_projection_roundtrip_and_utm_zone():
    assert geodesy.utm_crs_for(160.0, 65.5) == "EPSG:32657"
    assert geodesy.utm_crs_for(121.5, -30.75) == "EPSG:32751"
    # across the antimeridian, and across 0° in the 0–360° convention: the zone the points are in
    assert geodesy.utm_crs_for([179.8, -179.9, 179.95], [-17.0, -17.1, -17.2]) == "EPSG:32760"
    assert geodesy.utm_crs_for([-179.7, 179.9, -179.8], [52.0, 52.1, 52.2]) == "EPSG:32601"
    assert geodesy.utm_crs_for([359.6, 0.2, 359.9], [51.4, 51.5, 51.6]) == "EPSG:32630"
    e, n = geodesy.project_km([160.0, 160.1], [65.5, 65.5], "EPSG:32657")
    lon, lat = geodesy.unproject_km(e, n, "EPSG:32657")
    np.testing.assert_allclose(lon, [160.0, 160.1], atol=1e-9)
    np.testing.assert_allclose(lat, [65.5, 65.5], atol=1e-9)
    # 0.1° of longitude at 65.5° ≈ 4.63 km
    assert (e[1] - e[0]) == pytest.approx(111.32 * 0.1 * math.cos(math.radians(65.5)), rel=0.01)


def test_horizontal_velocity_misfit_finds_swapped_columns():
    """A track east at 100 m/s near −33°, −70°: the file's ve/vn agree with its positions
    (misfit ≪ 1 m/s); with lat and lon swapped, or ve and vn swapped, the misfit is of the
    order of the speed; a parked aircraft is not compared."""
    t = np.arange(0.0, 600.0, 0.1)
    lat = np.full(t.size, -33.0)
    r_m, r_n = geodesy.radii_of_curvature_m(lat)
    lon = -70.0 + np.rad2deg(100.0 * t / ((r_n + 3000.0) * np.cos(np.deg2rad(-33.0))))
    h = np.full(t.size, 3000.0)
    ve, vn = np.full(t.size, 100.0), np.zeros(t.size)
    speed, misfit, n = geodesy.horizontal_velocity_misfit_ms(t, lat, lon, h, ve, vn)
    assert speed == pytest.approx(100.0, rel=1e-3) and misfit < 0.05 and n == t.size
    _, misfit_swapped, _ = geodesy.horizontal_velocity_misfit_ms(t, lon, lat, h, ve, vn)
    assert misfit_swapped > 50.0
    _, misfit_en, _ = geodesy.horizontal_velocity_misfit_ms(t, lat, lon, h, vn, ve)
    assert misfit_en > 100.0
    parked = geodesy.horizontal_velocity_misfit_ms(t, lat, np.full(t.size, -70.0), h, 0 * ve, vn)
    assert parked[2] == 0


def test_grs80_normal_gravity_defining_values():
    """GRS80 (Moritz 1980): γ = 978 032.67715 mGal at the equator and 983 218.63685 mGal at the
    pole, on the ellipsoid; 0.143 mGal above WGS84 (γ_e 978 032.53359) everywhere."""
    g = geodesy.normal_gravity_mgal(np.array([0.0, 90.0, -90.0]), np.zeros(3), "GRS80")
    np.testing.assert_allclose(g, [978032.67715, 983218.63685, 983218.63685], atol=1e-4)
    lat = np.linspace(-90, 90, 37)
    d = geodesy.normal_gravity_mgal(lat, 3000.0, "GRS80") - geodesy.normal_gravity_mgal(lat, 3000.0, "WGS84")
    np.testing.assert_allclose(d, 978032.67715 - 978032.53359, atol=0.002)


def test_crs_fault_names_what_cannot_hold_a_survey():
    """UTM zones and a sane custom projection hold a survey; a geographic CRS, an unknown one
    and a Mercator with k = 1e-10 (parses, then fails on every point) do not."""
    assert geodesy.crs_fault("EPSG:32657") is None
    assert geodesy.crs_fault("+proj=tmerc +lon_0=158 +k=0.9996 +x_0=500000 +type=crs") is None
    assert "not a projected" in geodesy.crs_fault("EPSG:4326")
    assert "unknown CRS" in geodesy.crs_fault("EPSG:99999999")
    assert "projecting a point fails" in geodesy.crs_fault("+proj=merc +lon_0=158 +k=1e-10 +type=crs")


@pytest.mark.parametrize("units, name", [("km", "kilometre"), ("us-ft", "US survey foot"), ("ft", "foot")])
def test_crs_in_other_units_than_metres_refused(units, name):
    """Coordinates are read as metres everywhere (easting_km = x / 1000): a UTM zone written in
    km or feet projects (PROJ converts the test distance) but would put the survey 1000× or
    0.3048× its size on the map.  PROJ's own axis unit names it; in metres it passes."""
    zone = "+proj=utm +zone=57 +datum=WGS84 +type=crs"
    why = geodesy.crs_fault(f"{zone} +units={units}")
    assert why is not None and name in why and "metres" in why
    assert geodesy.crs_fault(f"{zone} +units=m") is None


@pytest.mark.parametrize("lon, lat, crs", [(159.0, 0.0, "EPSG:32657"), (162.0, 0.0, "EPSG:32657"),
                                           (159.0, 0.0, "EPSG:32655"), (159.0, 0.0, "EPSG:32651"),
                                           (159.0, 62.0, "EPSG:32651"), (-63.0, -35.0, "EPSG:32720")])
def test_scale_error_matches_proj_point_scale_factors(lon, lat, crs):
    """The distance error of a CRS at a point against PROJ's own scale factors there (meridional
    and parallel; UTM is conformal, so they agree), and UTM's k0 = 0.9996 at a zone's centre."""
    from pyproj import Proj

    f = Proj(crs).get_factors(lon, lat)
    want = max(f.meridional_scale - 1.0, f.parallel_scale - 1.0, key=abs)
    assert geodesy.scale_error(lon, lat, crs) == pytest.approx(want, rel=1e-3, abs=2e-5)   # 0.01° differences
    if (lon, lat, crs) == (159.0, 0.0, "EPSG:32657"):
        assert geodesy.scale_error(lon, lat, crs) == pytest.approx(0.9996 - 1.0, abs=2e-6)


@pytest.mark.parametrize("text, zone, north", [("UTM 57N", 57, True), ("utm zone 7 s", 7, False),
                                               ("WGS84 UTM 33N", 33, True)])
def test_epsg_for_text_names_the_zone_pyproj_knows(text, zone, north):
    """A UTM zone in words maps to the EPSG code whose PROJ definition is that zone and
    hemisphere (read back from pyproj), and a WKT to the code PROJ identifies; nonsense to None."""
    from pyproj import CRS

    code = geodesy.epsg_for_text(text)
    params = CRS.from_epsg(code).to_dict()
    assert params["proj"] == "utm" and params["zone"] == zone and ("south" in params) != north
    assert geodesy.epsg_for_text(CRS.from_epsg(32757).to_wkt()) == 32757
    assert geodesy.epsg_for_text("not a crs at all") is None
