"""Hybrid wheel/visual odometry (thesis ch. 2): the odometer core, the spherical remap, patch
search and voting, and a synthetic stereo world (`hybrid_vo.world`). No rclpy here; the ROS
node comes with the nodes issue."""
