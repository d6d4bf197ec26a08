"""Evaluation: OpenLex3D segmentation and retrieval, class-agnostic 3D instances, 2D source
tracks and segmenter masks (docs/architecture.md, "Evaluation protocol" and "Command-line
contract").

Public entry points, each returning a JSON-serialisable dict (undefined figures are None):

- :func:`eval_openlex3d` (``trackgraph eval openlex3d``),
- :func:`eval_instances` (``trackgraph eval instances``),
- :func:`eval_tracking` (``trackgraph eval tracking``),
- :func:`mean_best_iou` (per-image helper for ``trackgraph eval segmenter``),

plus the loaders (:func:`load_gt`, :func:`load_prediction`) and the track-map writer the
tracker uses for ``--save-tracks`` (:class:`TrackWriter`). Bad inputs raise
:class:`EvalInputError`, whose message starts with the offending file.
"""

from shared.eval.errors import EvalInputError
from shared.eval.gt import GroundTruth, ObjectLabels, Query, load_gt
from shared.eval.instances import eval_instances, evaluate_instances
from shared.eval.openlex3d import eval_openlex3d, evaluate_openlex3d
from shared.eval.prediction import Prediction, load_prediction, oracle_prediction, write_prediction
from shared.eval.segmenter import mean_best_iou
from shared.eval.text import TextEncoder, default_encoder
from shared.eval.track_io import (
    TrackWriter,
    read_instance_map,
    read_keyframes,
    read_track_map,
)
from shared.eval.tracking import eval_tracking, evaluate_track_maps

__all__ = [
    "EvalInputError",
    "GroundTruth",
    "ObjectLabels",
    "Prediction",
    "Query",
    "TextEncoder",
    "TrackWriter",
    "default_encoder",
    "eval_instances",
    "eval_openlex3d",
    "eval_tracking",
    "evaluate_instances",
    "evaluate_openlex3d",
    "evaluate_track_maps",
    "load_gt",
    "load_prediction",
    "mean_best_iou",
    "oracle_prediction",
    "read_instance_map",
    "read_keyframes",
    "read_track_map",
    "write_prediction",
]
