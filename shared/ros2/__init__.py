"""ROS 2 on the wire, without a ROS install: message types, the two Zenoh key conventions,
bags, SLAM corrections, and the markers the robot's stack shows (docs/ros2.md). The live
camera input's frame assembler belongs to the ROS 2 source service (services/ros2/live)."""
