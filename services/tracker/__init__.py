"""tracker: source-track propagation between keyframes and keyframe correction (paper III-B)."""
