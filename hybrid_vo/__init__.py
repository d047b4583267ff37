"""Hybrid wheel/visual odometry (thesis ch. 2): core and ROS node, coming in a later issue."""
