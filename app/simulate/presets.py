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
    turbulence_spectrum: str = "band"     # "band": flat between turbulence_band_hz; "peaked": PSD ∝ x^α/(1+x^(α+β))
    turbulence_peak_hz: float = 0.35      # x = f / turbulence_peak_hz ("peaked" only)
    turbulence_slopes: tuple[float, float] = (1.5, 6.0)     # (α, β): PSD rises as f^α, falls as f^−β
    # --- draped flight: height above height_m varies smoothly with position (terrain following)
    drape_amp_m: float = 0.0              # largest |drape| on the line windows (0: constant height)
    drape_wavelength_km: tuple[float, float] = (5.0, 15.0)
    drape_components: int = 12
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

    def replace(self, **overrides) -> "SimConfig":
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
}
