"""ROS 2 on the wire, without a ROS install: message types, the two Zenoh key conventions,
the live camera input, and the markers the robot's stack shows (docs/ros2.md)."""
