"""The ROS 2 node: the rclpy shell (``h2o_node``) over its rclpy-free ``mapper``.

Builds on :mod:`h2o_slam.core` and :mod:`h2o_slam.io`; message layouts live in
:mod:`msg_adapters`.
"""
