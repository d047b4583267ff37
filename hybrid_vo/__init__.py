"""Hybrid wheel/visual odometry (thesis ch. 2): the odometer core, the spherical remap, patch
search and voting, the front end without ROS, and the ROS node (``vo_node``). The simulator
the tests and benchmarks drive it with lives apart, in :mod:`hybrid_vo.sim`."""
