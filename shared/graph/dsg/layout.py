"""The layout of a trackgraph ``.sparkdsg``: Hydra's layer names, our node symbols and edge
kinds, the format version (the package docstring, :mod:`shared.graph.dsg`, says what goes where)."""

from __future__ import annotations

from typing import Literal

import spark_dsg as sd

LAYERS = sd.DsgLayers
HYDRA_LAYERS = (LAYERS.OBJECTS, LAYERS.AGENTS, LAYERS.PLACES, LAYERS.MESH_PLACES, LAYERS.ROOMS, LAYERS.BUILDINGS)
"""The layer names Hydra's ``SharedDsgInfo`` gives a graph; their keys come from spark_dsg."""
KEY_SEGMENT, KEY_PLACE, KEY_PLACE_2D, KEY_ROOM, KEY_BUILDING, KEY_AGENT = "O", "p", "Q", "R", "B", "a"
AGENT_PARTITION = KEY_AGENT
"""Hydra's agent partition is the robot prefix (kimera_pgmo's ``robot_id_to_prefix[0]``)."""
NO_LABEL = 2**32 - 1
UNKNOWN_ROOM = "unknown"
BUILDING_LABEL = 0
FORMAT_VERSION = 2
READABLE_FORMATS = (1, 2)
MeshColors = Literal["segments", "rgb"]

EDGE_KINDS = {
    (KEY_SEGMENT, KEY_PLACE): "segment_place",
    (KEY_PLACE, KEY_PLACE): "place_place",
    (KEY_PLACE, KEY_ROOM): "place_room",
    (KEY_ROOM, KEY_BUILDING): "room_building",
}
KEY_OF_KIND = {v: k for k, v in EDGE_KINDS.items()}
DERIVED_EDGES = {(KEY_AGENT, KEY_AGENT), (KEY_AGENT, KEY_PLACE), (KEY_PLACE, KEY_AGENT), (KEY_ROOM, KEY_ROOM), (KEY_PLACE_2D, KEY_PLACE_2D)}
KIND_ORDER = {"segment_place": 0, "place_place": 1, "place_room": 2, "room_building": 3}
