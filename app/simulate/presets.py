"""Simulation presets: one :class:`SimConfig` per named survey.

Every field can be overridden through ``simulate_survey(preset, out, **overrides)``
(tests shrink presets this way).  Units live in the names.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field


@dataclass(frozen=True)
class SimConfig:
    """Everything the simulator needs to build one survey.

    Geometry is laid out in the projected CRS around the survey centre: main lines
    run east–west (alternating headings), tie lines north–south across them, the
    repeat track east–west between two central main lines.
    """

    name: str = "survey"
    crs: str = "EPSG:32657"
    lat0_deg: float = 65.5
    lon0_deg: float = 160.0
    normal_gravity: str = "WGS84"
    # --- geometry / flight plan
    height_m: float = 3000.0
    speed_ms: float = 100.0
    n_main: int = 4
    main_length_km: float = 30.0
    main_spacing_km: float = 2.0
    n_tie: int = 2
    tie_margin_km: float = 2.0            # tie lines extend this far beyond the outer main lines
    n_repeat: int = 0                     # times the repeat track is flown (0: no repeat track)
    repeat_length_km: float | None = None  # None: main_length_km
    repeat_alternate: bool = False        # repeat passes alternate direction (reversal turns between)
    wind_ms: float = 0.0                  # ground speed on a line = speed_ms + wind_ms·(east component of heading)
    n_flights: int = 1
    run_in_s: float = 30.0                # straight level flight before each line window
    run_out_s: float = 10.0               # after each line window
    turn_s: tuple[float, float] = (60.0, 90.0)
    lead_s: float = 120.0                 # flight data before the first run-in
    tail_s: float = 120.0                 # after the last run-out
    flight_spacing_s: float = 86400.0     # flights on successive days
    epoch_offset_s: float = 3.0 * 3600.0  # first flight starts this long after the time origin
    # --- anomaly field ("sources") or Markov-jump model ("markov")
    field_kind: str = "sources"
    grid_spacing_km: float = 0.5
    grid_margin_km: float = 8.0
    mountain_std_mgal: float = 20.0
    plain_std_mgal: float = 8.0
    mountain_sources_per_km2: float = 0.25
    mountain_depth_m: tuple[float, float] = (300.0, 2500.0)  # below a 500 m surface
    mountain_bodies: str = "points"       # "points": point masses; "prisms": blocks (field._mountain_prisms)
    prism_size_km: tuple[float, float] = (0.5, 4.0)        # horizontal sides of the prisms
    prism_thickness_m: tuple[float, float] = (300.0, 3000.0)
    plain_sources_per_km2: float = 0.01
    plain_depth_m: tuple[float, float] = (6000.0, 20000.0)  # depth range of the plain sources
    field_std_over: str = "grid"          # "grid": *_std_mgal over the truth grid; "lines": along the line windows
    # --- Markov-jump anomaly (field_kind == "markov"; seed 000 Table 1/2)
    markov_Q_mgal2: tuple[float, float] = (0.0414, 0.3533)
    markov_a11: float = 0.9876
    markov_a22: float = 0.9697
    markov_block_epochs: int = 100        # states held constant on blocks of this many GNSS epochs
    markov_map_step_km: float = 1.0
    markov_dg0_std_mgal: float = 10.0
    # --- aircraft vertical motion
    fine_rate_hz: float = 100.0
    turbulence_rms_ms2: tuple[float, float] = (0.15, 0.6)   # range of per-flight RMS vertical acceleration
    turbulence_band_hz: tuple[float, float] = (0.08, 0.8)
    motion_max_hz: float = 2.0
    phugoid_amp_m: float = 3.0
    phugoid_period_s: tuple[float, float] = (40.0, 120.0)
    horizontal_noise_ms2: float = 0.01
    turbulence_envelope_log_std: float = 0.5   # intensity = level·exp(this·N(0,1)) (10-min correlation)
    turbulence_spectrum: str = "band"     # "band": flat between turbulence_band_hz; "peaked": PSD ∝ x^α/(1+x^(α+β))
    turbulence_peak_hz: float = 0.35      # x = f / turbulence_peak_hz ("peaked" only)
    turbulence_slopes: tuple[float, float] = (1.5, 6.0)     # (α, β): PSD rises as f^α, falls as f^−β
    # --- draped flight: height above height_m varies smoothly with position (terrain following)
    drape_amp_m: float = 0.0              # the height spans height_m ± this on the line windows (0: constant)
    drape_wavelength_km: tuple[float, float] = (5.0, 15.0)
    drape_components: int = 12
    repeat_height_offsets_m: tuple[float, ...] = ()  # repeat pass r flies offsets[r % len] higher (m), held
    #                                                  over its run-in, window and run-out, eased (cosine) in the
    #                                                  turns; () = every pass at the same height
    # --- topography as prisms (0: none); docs/SIMULATOR.md, app/simulate/topography.py
    topo_amp_m: float = 0.0               # terrain spans topo_base_m ± this over the DEM
    topo_base_m: float = 700.0
    topo_wavelength_km: tuple[float, float] = (3.0, 25.0)
    topo_components: int = 24
    topo_density_kgm3: float = 2670.0
    topo_spacing_m: float = 250.0         # DEM cell size (each cell one prism from 0 m to its height)
    topo_margin_km: float = 10.0          # DEM beyond the flight paths (the terrain radius it supports)
    topo_clearance_m: float = 0.0         # > 0: terrain-following flight this far above the smoothed terrain
    topo_drape_smooth_km: float = 2.0     # Gaussian smoothing of the terrain the aircraft follows
    # --- gravimeter
    gravimeter_model: str = "GT-1A"
    gravimeter_rate_hz: float = 18.24
    tau_true_s: float = 2.0
    scale_true: float = 1.0 + 2e-4
    tau_declared_s: float = 2.0
    scale_declared: float = 1.0
    drift_rate_mgal_h: tuple[float, float] = (0.5, 2.0)     # |rate| range, random sign
    drift_offset_std_mgal: float = 2.0
    drift_rw_mgal_rth: float = 0.2                          # random walk density, mGal/sqrt(h)
    grav_noise_mgal_rthz: float = 0.5                       # white sensor noise density, mGal/sqrt(Hz)
    time_offset_s: float = 0.0                              # gravimeter stamp = true time + offset
    gravimeter_sampling: str = "mean"     # "mean": interval means; "point": instantaneous output at the stamp
    gravimeter_clock: str = "free"        # "free": free-running clock (random phase, stamps at interval
    #                                       centres, rounded to 1 ms); "aligned": samples at exact multiples
    #                                       of the period (mean intervals centred on them)
    gravimeter_fir_boxcars: int = 0       # internal zero-phase FIR (unknown to processing): this many
    gravimeter_fir_width_s: float = 0.0   # cascaded boxcars of this width, H(f) = sinc(f·W)^n
    # --- parking place (base) readings: the aircraft stands still on the apron before and after
    #     every flight (0 disables); taxi and climb between apron and survey are not recorded
    apron_s: float = 300.0                # length of each static segment (GNSS span)
    apron_gap_s: float = 600.0            # unrecorded time between an apron segment and the airborne data
    airport_km: tuple[float, float] | None = None   # (east, north) from the survey centre; None: 20 km
    #                                                 west of the west end of the main lines
    airport_h_m: float = 200.0            # ellipsoidal height of the gravimeter on the apron
    airport_anomaly_mgal: float = 35.0    # g_base = γ(airport) + this (local anomaly), rounded to 0.01 mGal
    # --- GNSS
    gnss_rate_hz: float = 10.0
    gnss_velocity: bool = True            # False: heights-only GNSS (gnss.csv = time, lat, lon, h)
    h_colored_m: float = 0.0              # Gauss–Markov GNSS height error, std (m), on top of sigma_h_m
    h_colored_tau_s: float = 30.0         # its correlation time
    sigma_vu_cms: float = 1.3
    vu_colored_cms: float = 0.0          # extra exponentially correlated (Gauss-Markov) vu error, std
    vu_colored_tau_s: float = 5.0        # its correlation time
    vu_from_position_m: float = 0.0      # extra vu error from differenced white position noise, std (m)
    sigma_vh_cms: float = 1.0
    sigma_pos_m: float = 0.02
    sigma_h_m: float = 0.03
    episode_rate_per_h: float = 1.5
    episode_len_s: tuple[float, float] = (60.0, 300.0)
    episode_factor: tuple[float, float] = (3.0, 5.0)        # std multiplier during noisy episodes
    # --- output
    compress: bool = False
    processing: dict = field(default_factory=dict)         # written to [processing] of survey.toml

    def replace(self, **overrides) -> SimConfig:
        """Copy with fields replaced; unknown names raise ``TypeError``."""
        names = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(overrides) - names)
        if bad:
            raise TypeError(f"unknown simulation parameter(s): {', '.join(bad)}")
        return dataclasses.replace(self, **overrides)


PRESETS: dict[str, SimConfig] = {
    "tiny": SimConfig(
        name="tiny", n_main=4, main_length_km=30.0, n_tie=2, n_flights=1,
        grid_margin_km=6.0, time_offset_s=0.0),
    "omolon-mini": SimConfig(
        name="omolon-mini", n_main=10, main_length_km=60.0, n_tie=3, n_repeat=3, repeat_length_km=30.0,
        n_flights=3,
        time_offset_s=0.05, compress=True,
        apron_s=120.0),                   # short base readings: the committed sample stays ≤ 7 MB
    "omolon": SimConfig(
        name="omolon", n_main=57, main_length_km=200.0, main_spacing_km=2.0, n_tie=17,
        n_flights=12, mountain_sources_per_km2=0.15, time_offset_s=0.05),
    "kalgoorlie": SimConfig(
        name="kalgoorlie", crs="EPSG:32751", lat0_deg=-30.75, lon0_deg=121.5,
        normal_gravity="Helmert1901", height_m=800.0, speed_ms=70.0,
        n_main=40, main_length_km=80.0, main_spacing_km=2.0, n_tie=7, n_repeat=3,
        n_flights=10, mountain_std_mgal=15.0, plain_std_mgal=10.0,
        mountain_sources_per_km2=0.15, mountain_depth_m=(1000.0, 3000.0),
        turbulence_rms_ms2=(0.3, 1.0), sigma_vu_cms=1.5, airport_h_m=360.0, airport_anomaly_mgal=-22.0),
    "markov": SimConfig(
        name="markov", field_kind="markov", n_main=50, main_length_km=110.0, main_spacing_km=2.0,
        n_tie=0, n_flights=9, sigma_vu_cms=float(1.6787 ** 0.5), episode_rate_per_h=0.0,
        time_offset_s=0.0, processing={"m": 1}),
    # ---------------------------------------------------------------- realistic regimes
    # (docs/SIMULATOR.md has the table; truth/ as for the presets above, plus h_true_m when the height
    # matters).  The real 2 Hz test line (/work/shared/notes/real-line-noise-spectrum.md): platform
    # gravimeter (AIRGrav class) at 2 Hz, heights-only GNSS at 2 Hz, one 40 km line flown 4x in
    # alternating directions at 55-66 m/s, ~330 m above the ellipsoid, draped +-45 m, heavy turbulence
    # (f_z std 0.60-0.64 m/s², ḧ std 0.67-0.74 m/s², z std 0.34-0.41 m/s²), anomaly along-line std
    # 8.5 mGal with wavelengths >= 6 km.
    #  * track: repeat R1 (4 passes, alternating), no main/tie lines, no crossings; ground speed
    #    60.5 +- 5.5 m/s (wind 5.5 m/s towards the east: 66 m/s eastbound, 55 m/s westbound);
    #    reversal turns (straight on, U-turn, S-curve back onto the track)
    #  * height 330 m + drape (330 +- 45 m on the line; plane waves of 15-40 km wavelength: with the
    #    unknown lag below, drape waves of 5-15 km would put 20-50 mGal into 0.005-0.02 Hz, where the
    #    real line has 2-8 mGal); phugoid 0.3 m
    #  * turbulence: peaked spectrum, PSD ∝ x^3/(1+x^11), x = f/0.4 Hz, level 0.75-0.85 m/s² with a
    #    weakly varying intensity (log-std 0.15): realised f_z std ≈ 0.62 m/s², ḧ std ≈ 0.71 m/s²
    #  * motion mismatch (unknown to the processing, survey.toml declares tau_s = 0):
    #    - a residual first-order lag tau = 0.25 s in the instrument (0.85∠-32° at 0.4 Hz), and
    #    - its 2 Hz decimation (anti-alias) filter: zero-phase sinc², two boxcars of 0.5 s
    #      (0.98 at 0.1 Hz, 0.88 at 0.4 Hz, 0.41 at 1 Hz, double zeros at multiples of 2 Hz);
    #    total 0.74∠-32° at 0.4 Hz: z ≈ 0.5 of the aircraft acceleration above 0.1 Hz
    #  * gravimeter: point samples of that output at exact multiples of 0.5 s
    #  * GNSS: 2 Hz, time/lat/lon/h only; height error 7 mm white + 2.5 cm Gauss-Markov (tau 60 s)
    #  * field: plain sources only, 3-10 km deep, std 8.5 mGal along the line
    "testline-2hz": SimConfig(
        name="testline-2hz", height_m=330.0, speed_ms=60.5, wind_ms=5.5,
        n_main=0, n_tie=0, main_length_km=40.0, n_repeat=4, repeat_length_km=40.0, repeat_alternate=True,
        n_flights=1, turn_s=(70.0, 80.0),
        mountain_sources_per_km2=0.0, plain_std_mgal=8.5, plain_sources_per_km2=0.05,
        plain_depth_m=(3000.0, 10000.0), field_std_over="lines",
        turbulence_spectrum="peaked", turbulence_peak_hz=0.4, turbulence_slopes=(3.0, 8.0),
        turbulence_rms_ms2=(0.75, 0.85), turbulence_envelope_log_std=0.15, phugoid_amp_m=0.3,
        drape_amp_m=45.0, drape_wavelength_km=(15.0, 40.0),
        gravimeter_model="AIRGrav", gravimeter_rate_hz=2.0, gravimeter_sampling="point",
        gravimeter_clock="aligned", gravimeter_fir_boxcars=2, gravimeter_fir_width_s=0.5,
        tau_true_s=0.25, tau_declared_s=0.0, time_offset_s=0.0,
        gnss_rate_hz=2.0, gnss_velocity=False, sigma_h_m=0.007, h_colored_m=0.025, h_colored_tau_s=60.0),
}


# ---------------------------------------------------------------- single-regime variants for sweeps
# omolon-mini's geometry, field and noise (10 main lines of 60 km, 3 ties, 3 repeats, 3 flights) with
# one regime switched on; docs/SIMULATOR.md lists the numbers.
_MINI = PRESETS["omolon-mini"]
#: platform gravimeter: no lag (tau 0 true and declared), samples at exact multiples of the period
_PLATFORM = dict(gravimeter_model="AIRGrav", tau_true_s=0.0, tau_declared_s=0.0, time_offset_s=0.0,
                 gravimeter_clock="aligned")
#: heights-only GNSS: 7 mm white + 2.5 cm Gauss-Markov (60 s) height error, no velocity columns
_HEIGHTS_ONLY = dict(gnss_velocity=False, sigma_h_m=0.007, h_colored_m=0.025, h_colored_tau_s=60.0)
#: heavy turbulence with a real aircraft's spectrum (most power 0.1-0.5 Hz)
_TURBULENT = dict(turbulence_spectrum="peaked", turbulence_peak_hz=0.4, turbulence_slopes=(3.0, 8.0),
                  turbulence_rms_ms2=(0.3, 0.5))
PRESETS.update({
    # interval means at 1 Hz / 2 Hz (the mean is the instrument's decimation filter)
    "platform-1hz": _MINI.replace(name="platform-1hz", gravimeter_rate_hz=1.0, gravimeter_sampling="mean",
                                  **_PLATFORM),
    "platform-2hz": _MINI.replace(name="platform-2hz", gravimeter_rate_hz=2.0, gravimeter_sampling="mean",
                                  **_PLATFORM),
    # point samples after a zero-phase sinc² decimation filter (two boxcars of one output period),
    # unknown to the processing
    "platform-2hz-point": _MINI.replace(name="platform-2hz-point", gravimeter_rate_hz=2.0,
                                        gravimeter_sampling="point", gravimeter_fir_boxcars=2,
                                        gravimeter_fir_width_s=0.5, **_PLATFORM),
    "platform-10hz-point": _MINI.replace(name="platform-10hz-point", gravimeter_rate_hz=10.0,
                                         gravimeter_sampling="point", gravimeter_fir_boxcars=2,
                                         gravimeter_fir_width_s=0.1, **_PLATFORM),
    "heights-only-1hz": _MINI.replace(name="heights-only-1hz", gnss_rate_hz=1.0, **_HEIGHTS_ONLY),
    "heights-only-5hz": _MINI.replace(name="heights-only-5hz", gnss_rate_hz=5.0, **_HEIGHTS_ONLY),
    "heights-only-10hz": _MINI.replace(name="heights-only-10hz", gnss_rate_hz=10.0, **_HEIGHTS_ONLY),
    "turbulent": _MINI.replace(name="turbulent", **_TURBULENT),
    # draped +-50 m along the lines (plane waves of 5-15 km), truth at the actual height
    "draped": _MINI.replace(name="draped", drape_amp_m=50.0, drape_wavelength_km=(5.0, 15.0)),
})

# ---------------------------------------------------------------- topography (terrain and Bouguer products)
#  tiny's geometry (4 x 30 km, 2 ties) + 2 repeat passes; terrain 700 +- 450 m (waves 3-25 km) as 250 m
#  prisms of 2670 kg/m3 over the flight paths + 10 km, written to dem.tif; terrain-following flight
#  400 m above the terrain smoothed over 2 km; truth: terrain_mgal per epoch, included in dg_true_mgal
_TOPO = dict(topo_amp_m=450.0, topo_base_m=700.0, topo_clearance_m=400.0, height_m=1100.0, n_repeat=2, repeat_length_km=20.0,
             grid_margin_km=6.0)
PRESETS.update({
    # the anomaly is the topography's gravity only (no point sources): the Bouguer anomaly is flat
    "topo-only": PRESETS["tiny"].replace(name="topo-only", mountain_sources_per_km2=0.0, plain_std_mgal=0.0,
                                         **_TOPO),
    # the topography's gravity plus tiny's point sources
    "topo-draped": PRESETS["tiny"].replace(name="topo-draped", **_TOPO),
})

#: one line per preset (``aerograv simulate --help``; the numbers are in docs/SIMULATOR.md)
PRESET_NOTES: dict[str, str] = {
    "tiny": "4 x 30 km lines, 2 ties, 1 flight (GT-1A 18.24 Hz, 10 Hz GNSS with vu)",
    "omolon-mini": "10 x 60 km, 3 ties, 3 repeats, 3 flights (the bundled sample, seed 1)",
    "omolon": "57 x 200 km, 17 ties, 12 flights",
    "kalgoorlie": "40 x 80 km, 7 ties, 3 repeats, 10 flights, 800 m, Helmert 1901",
    "markov": "50 x 110 km, Markov-jump anomaly with seed 000's Q and transitions",
    "testline-2hz": "the real 2 Hz test line: 40 km x 4 passes, 2 Hz platform + heights-only GNSS, draped",
    "platform-1hz": "omolon-mini, platform gravimeter, 1 Hz interval means, tau 0",
    "platform-2hz": "omolon-mini, platform gravimeter, 2 Hz interval means, tau 0",
    "platform-2hz-point": "omolon-mini, platform gravimeter, 2 Hz point samples behind a sinc^2 filter",
    "platform-10hz-point": "omolon-mini, platform gravimeter, 10 Hz point samples behind a sinc^2 filter",
    "heights-only-1hz": "omolon-mini, GNSS 1 Hz time/lat/lon/h only (2.5 cm Gauss-Markov + 7 mm white)",
    "heights-only-5hz": "omolon-mini, GNSS 5 Hz time/lat/lon/h only (2.5 cm Gauss-Markov + 7 mm white)",
    "heights-only-10hz": "omolon-mini, GNSS 10 Hz time/lat/lon/h only (2.5 cm Gauss-Markov + 7 mm white)",
    "turbulent": "omolon-mini, heavy turbulence 0.3-0.5 m/s2 with a peaked (0.1-0.5 Hz) spectrum",
    "draped": "omolon-mini, height 3000 +- 50 m along the lines (5-15 km waves), truth at the actual height",
    "topo-only": "tiny + 2 repeats over a 250 m prism DEM (700 +- 450 m, dem.tif), flown 400 m above it; "
                 "anomaly = the topography only",
    "topo-draped": "as topo-only, anomaly = topography + tiny's point sources",
}
assert set(PRESET_NOTES) == set(PRESETS)
