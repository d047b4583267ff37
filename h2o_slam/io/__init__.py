"""Files: g2o graphs, the saved map, synthetic datasets, bags and replay outputs.

Builds on :mod:`h2o_slam.core` only; rclpy is imported lazily, by the bag writer alone.
"""
