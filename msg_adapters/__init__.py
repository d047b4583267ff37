"""Pure functions between ROS messages and core types, with validation (later issue)."""
