"""Research filters: experiments from the seed papers that the product never runs.

* :mod:`app.research.two_filter` — seed 002: two-filter (Fraser–Potter) fixed-interval
  smoother, compared with RTS in ``benchmarks/seed002_sphere.py``;
* :mod:`app.research.random_walk_kf` — seed 003: scalar random-walk Kalman filter + RTS
  smoother with Q by maximum likelihood;
* :mod:`app.research.position_domain` — seed 004: position-domain Kalman filter/RTS
  smoother with the gravimeter reading as control input.

Dependencies go one way: ``app.research`` may import ``app.core``; ``app.core``,
``app.pipeline`` and ``app.web`` never import ``app.research`` (checked by
``tests/research/test_layering.py``).  Tested in ``tests/research/``.
"""
