"""keyframe_vl: class-agnostic masks and CLIP features at keyframes, and the embedding API."""
