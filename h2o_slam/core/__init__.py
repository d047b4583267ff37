"""The solver core: pose-graph mathematics, H₂O's updates, exact mode and LAGO.

Plain numpy/scipy/numba libraries: no file formats, no rclpy, no plotting. Everything
else in the package builds on this layer (``test/test_layering.py`` holds it to that).
"""
