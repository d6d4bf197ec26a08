"""The source service: replays a recorded sequence as ``frames`` over Zenoh."""
