"""The named stages of the method (SPEC §2 and §3), one module each, on plain data.

A survey runs through them in this order (:mod:`app.pipeline.runs` ties them together,
:func:`app.pipeline.process.process_survey` is ``aerograv process``):

1. :mod:`~.measurement` — corrections and z_k per flight, lag check, time offset, gaps,
   spikes, base ties → :class:`~.measurement.Measurement`;
2. :mod:`~.lines` — the survey lines cut out of their flights → :class:`~.lines.SurveyLines`;
3. :mod:`~.noise` — the error of z as a coloured process and its level in time →
   :class:`~.noise.NoiseStage`;
4. :mod:`~.model_order` — which anomaly orders m to identify;
5. :mod:`~.regularization`, :mod:`~.learning`, :mod:`~.recognition` (together
   :mod:`~.identification`) — ∇^m, Kaiser low-pass, decimation, MA; EM; Viterbi and
   posteriors → :class:`~.identification.Identification`;
6. :mod:`~.recognition` — NL-means of the map (h, ρ) and the state choice →
   :class:`~.recognition.StateMap`;
7. :mod:`~.filtering` — the non-stationary Kalman smoother, stationary and FIR beside it →
   :class:`~.filtering.Filtered`;
8. :mod:`~.choice` — which estimate (and which m) becomes dg, from the data alone →
   :class:`~.choice.ModelChoice`;
9. :mod:`~.leveling` — crossovers, drift, F-test, std check → :class:`~.leveling.Leveled`;
10. :mod:`~.gridding` — collocation map with its std → :class:`~.gridding.Gridded`;
11. :mod:`~.outputs` — identification.json, report.json and the files of SPEC §5.

Every result is a dataclass that :mod:`~.storage` can store and load.
"""
