"""ROS 2 on the wire: the live source, the markers-and-queries bridge, the bag player."""
