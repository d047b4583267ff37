"""The shell both ROS 2 nodes share (``h2o_node`` and ``hybrid_vo_node``): parameters
declared from a configuration tree, the boundary every callback runs behind, each input's
messages accounted for, outputs by key, ``/tf`` and ``/diagnostics``, and the ``main`` that
spins a node.

A package of its own so that the packages depend one way: it sits on rclpy,
:mod:`msg_adapters` and :mod:`h2o_slam.core` only, and both :mod:`h2o_slam.ros` and
:mod:`hybrid_vo` build on it without importing each other (only :mod:`h2o_slam.app` joins
the two nodes). Inside :mod:`h2o_slam` it would have tied ``hybrid_vo`` to the back end's
package; inside ``hybrid_vo``, the back end to the odometer's.
"""
