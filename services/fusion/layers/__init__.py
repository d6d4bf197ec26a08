"""The scene-graph layers fusion builds from the volume's mesh: persistent 3D segments with
re-identification and CLIP galleries (III-D to III-F), the surface sample, places, rooms and
their names (Hydra's hierarchy).

``segments`` (the layer) builds on ``segment`` (one node), ``overlap`` (eq. 7), ``reid``
(eqs. 8-9) and ``gallery``; ``places``, ``rooms`` and ``roomnames`` build the hierarchy above."""
