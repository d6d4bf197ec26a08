"""Pose corrections: the poses each frame was fused with, how a SLAM back end's correction
changes them, the corrections waiting for their frame, and the log of fused frames kept to
re-fuse the map at corrected poses."""
