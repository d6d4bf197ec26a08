"""TrackGraph's services: source, tracker, keyframe_vl, fusion, query, and the CLI."""
