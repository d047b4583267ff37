"""The simulator the tests, the benchmarks and ``h2o-demo`` drive the system with: a seeded
synthetic stereo world (:mod:`hybrid_vo.sim.world`) and its drives as the ROS messages a
robot would record (:mod:`hybrid_vo.sim.messages`).

Not part of the odometer: builds on the odometer's camera model and frames and on
:mod:`msg_adapters`; no other module of :mod:`hybrid_vo` imports it, and in
:mod:`h2o_slam` only the applications do (``test/test_layering.py``).
"""
