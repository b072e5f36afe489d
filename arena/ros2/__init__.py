"""Every Arena robot a ROS 2 node over Zenoh, in rmw_zenoh's wire format (specs/ros2.md)."""
