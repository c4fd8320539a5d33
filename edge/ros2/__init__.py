"""ROS 2 sees dynqos natively: its topics in rmw_zenoh's wire format (docs/ros2.md)."""
