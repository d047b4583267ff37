"""Baselines the benchmarks and tests compare H₂O against: TORO, Carlone et al.'s covariance
variants, and χ² as GTSAM and g2o compute it.

Not part of the solver: builds on :mod:`h2o_slam.core` only, and the core never imports it
(``test/test_layering.py`` holds both to that). ``h2o-solve`` reports the other tools' χ²
from here.
"""
