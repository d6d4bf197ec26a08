"""Map viewer: Rerun recordings of the scene graph, PNG renders, and the live viewer node."""
