"""fusion: TSDF with source-track hypotheses, persistent 3D segments, re-identification and the
hierarchical scene graph (paper sections III-A, III-C, III-D, III-E)."""
