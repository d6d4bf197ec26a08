"""Model files: what a config needs, whether it loads (``trackgraph models check``), and ONNX
export of the configured models (``trackgraph export-onnx``)."""
