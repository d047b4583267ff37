"""Applications: bag replay through both nodes, and the commands (``h2o-solve``,
``h2o-replay``, ``h2o-demo``).

The only layer that may import :mod:`hybrid_vo`, which itself sits beside
:mod:`h2o_slam.ros`.
"""
