"""Export of the scene graph to spark_dsg (Hydra's scene-graph library, 1.1) and back.

A saved ``.sparkdsg`` opens in Hydra's tools with the layers, partitions, symbols and
attribute types Hydra itself writes. The graph is built with Hydra's layer map
(``hydra::SharedDsgInfo::Config``), every key taken from
``spark_dsg.DsgLayers.name_to_layer_id`` and saved with the file's layer names:
``OBJECTS`` 2, ``AGENTS`` 2, ``PLACES`` 3, ``MESH_PLACES`` 3[1], ``ROOMS`` 4, ``BUILDINGS`` 5.

| ours | layer | symbol | spark_dsg attributes |
|---|---|---|---|
| segment | ``OBJECTS`` | ``O<id>`` | ``ObjectNodeAttributes``: box, CLIP gallery as ``semantic_feature``, mesh connections, colour |
| place | ``PLACES`` | ``p<id>`` | ``PlaceNodeAttributes``: ``distance`` = radius, ``is_active``, ``real_place``, colour |
| place outline | ``MESH_PLACES`` | ``Q<id>`` | ``Place2dNodeAttributes``: ``boundary``, Hydra's ellipse, ``is_active``, colour |
| room | ``ROOMS`` | ``R<id>`` | ``RoomNodeAttributes``: name, box, ``semantic_label``, colour, feature as a one-row ``semantic_feature`` |
| building | ``BUILDINGS`` | ``B0`` | ``SemanticNodeAttributes`` at the mean of the room centroids |
| camera pose | ``AGENTS``, partition ``'a'`` | ``a<row>`` | ``AgentNodeAttributes``: position, ``world_R_body``, timestamp |
| mesh | the graph's mesh | | positions, segment colours, per-vertex label = segment id |

**Places: two nodes, one per Hydra place type.** No spark_dsg 1.1 attribute type holds both
a free-space distance and an outline: ``PlaceNodeAttributes`` has ``distance`` and no
boundary, ``Place2dNodeAttributes`` a ``boundary`` and no distance (the third,
``TraversabilityNodeAttributes``, has a grid-aligned box, not a polygon, and Hydra writes no
such layer). Hydra writes its GVD places into ``PLACES`` as ``PlaceNodeAttributes`` with
prefix ``p``, and its code reads them as such: the room finder, the MST factors, the
frontier and descriptor code call ``attributes<PlaceNodeAttributes>()`` on ``PLACES`` nodes
and read ``distance``, and ``UpdateRoomsFunctor`` keeps nodes of category ``p``. Its 2D
places go into ``MESH_PLACES`` (layer 3, partition 1) as ``Place2dNodeAttributes`` with
prefix ``Q`` (``Place2dSegmenter``): ``boundary`` (the convex hull of the region, 3D
points), ``ellipse_centroid`` and ``ellipse_matrix_expand/compress`` from the minimum-area
rectangle (``addRectInfo``, which its place-connection test reads). So each place is a ``p``
node carrying the hierarchy (segment -> place -> room edges, the distance, the active flag)
and, when it has an outline, a ``Q`` node with the same id carrying it: the outline as
written (world xy at the place's height, in its own order, so it reads back exactly) and
the ellipse of its minimum-area rectangle as Hydra computes it. The ``Q`` nodes repeat the
place-place edges among themselves, as Hydra's 2D places have edges of their own.

**Derived edges**, written for Hydra's tools and skipped by :func:`from_dsg`, which rebuilds
them on the next export: consecutive agent nodes are joined (Hydra's pose-graph odometry
edges); each agent node is a child of one place (Hydra's ``LayerConnector`` makes the
nearest place the single parent of every node of layer 2, agents included): the nearest
place whose outline contains the pose's xy, else the nearest place; rooms whose places are
joined by a place-place edge are joined (``addEdgesToRoomLayer``).

**Agents** follow ``PoseGraphPacket::addToGraph``: layer ``AGENTS``'s id with partition = the
robot prefix (robot 0, ``'a'``), symbol ``a<k>`` for trajectory row k (Hydra numbers pose
keys from 0, and ``UpdateFrontiersFunctor`` takes ``a<num_nodes - 1>`` as the latest pose),
``external_key`` = the node's own symbol. The snapshot carries frame indices, not clock
times, and spark_dsg's Python binding passes ``timestamp`` as a ``datetime.timedelta``
(microsecond resolution), so the timestamp is the frame index in microseconds
(``timestamp.count() == 1000 * frame`` ns): Hydra only orders agents by stamp and looks up
the nearest one. The frame index is also in the node's metadata.

**Colours and labels.** Every semantic node has a ``color``: segments the colour of
:func:`shared.graph.colors.segment_colors` for their id (the viewer's palette, so a
segment looks the same in the recording, the PNG renders and Hydra's tools), rooms the same
palette for their id, places their room's colour (grey without a room), the building grey.
Mesh vertices with a segment take their segment's colour; vertices without one keep their
RGB. With ``mesh_colors="segments"`` (the default) the original RGB of the segmented vertices
is kept in the graph metadata (``mesh_rgb``: zlib + base64 of the (V_s, 3) uint8 rows in
vertex order) so :func:`from_dsg` restores the mesh exactly; ``mesh_colors="rgb"`` writes the
RGB as is. Rooms get a ``semantic_label`` from their name in a label space registered with
``DynamicSceneGraph.set_labelspace`` on the ``ROOMS`` layer key (label 0 = ``unknown`` for an
unnamed room, as Hydra's room finder gives label 0; the other names sorted, from 1), the
building label 0 of a ``BUILDINGS`` label space ``{0: "building"}``. Segments are
class-agnostic and places are free space, so both keep ``NO_SEMANTIC_LABEL`` and no label
space is registered for their layers; the mesh labels are segment ids, not classes, so no
``mesh`` label space either (Hydra's would map classes).

A segment's ``semantic_feature`` holds its whole CLIP gallery, one row per gallery track
(a float16 gallery is widened to float32 there; its dtype is kept in the metadata and
restored). The segment's ``mesh_connections`` list its mesh vertices, as Hydra's objects
do. What spark_dsg has no field for goes into the node's JSON metadata under
``"trackgraph"``: the tracks, gallery tracks and weights, the DINOv3 feature, the segment's
flags, room and vertex count, the float64 boxes (the attributes hold float32 boxes), a room's float64 box (absent
when the room had none: then the attribute box comes from its places' outlines), area, an
agent's frame index. Mesh vertices without a segment carry the
label 2**32 - 1. The graph metadata records the format version and this layout. Outline
hulls and the agent-place lookup use scipy (``ConvexHull``, ``cKDTree``). spark-dsg comes with
the ``hydra`` extra (in ``all``); without it fusion logs a warning and saves maps without
``graph.sparkdsg`` (its wheels need an sdist-only ``zmq``, so a robot profile leaves it out).

:func:`from_dsg` rebuilds the :class:`GraphSnapshot` (for float32 galleries exactly), and
still reads files of format 1 (no outlines, agents, room boxes or segment colours).

The package: :mod:`~shared.graph.dsg.layout` (layers, symbols, edge kinds, format version),
:mod:`~shared.graph.dsg.write` (:func:`to_dsg`), :mod:`~shared.graph.dsg.hydra` (what Hydra
derives: outlines and ellipses, room boxes, agent places, derived edges),
:mod:`~shared.graph.dsg.read` (:func:`from_dsg`); here, saving and loading a file.
"""

from __future__ import annotations

from pathlib import Path

import spark_dsg as sd

from shared.graph.dsg.layout import MeshColors
from shared.graph.dsg.read import from_dsg
from shared.graph.dsg.write import to_dsg
from shared.io import atomic_replace
from shared.messages.graph import GraphSnapshot

__all__ = ["from_dsg", "load_dsg", "save_dsg", "to_dsg"]


def save_dsg(snap: GraphSnapshot, path: Path | str, include_mesh: bool = True, mesh_colors: MeshColors = "segments") -> Path:
    """Write ``path`` (.sparkdsg) atomically (:func:`shared.io.atomic_replace`): spark_dsg
    writes a temporary ``.sparkdsg`` in the same folder, renamed over ``path`` once fsynced.
    ``mesh_colors`` as in :func:`to_dsg`."""
    g = to_dsg(snap if include_mesh else snap.model_copy(update={"mesh": None}), mesh_colors=mesh_colors)
    return atomic_replace(Path(path), lambda tmp: g.save(str(tmp), include_mesh=include_mesh), suffix=".tmp.sparkdsg")


def load_dsg(path: Path | str) -> GraphSnapshot:
    """Read a ``.sparkdsg`` written by :func:`save_dsg`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no scene graph at {path}")
    return from_dsg(sd.DynamicSceneGraph.load(str(path)))
