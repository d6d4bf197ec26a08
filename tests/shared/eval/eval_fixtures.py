"""Hand-built evaluation inputs: a one-hot text encoder, lattice objects and file writers.

Objects are filled lattices of points 0.02 m apart, offset 0.005 m from a 0.1 m grid, so no
point lies near a 0.05 m voxel boundary and every ground-truth point's nearest downsampled
point is the centroid of its own voxel (at most sqrt(3) * 0.02 m away: never "missing").
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.eval.prediction import write_prediction


class VocabEncoder:
    """One orthogonal unit vector per known text: cosine 1 with itself, 0 with the others."""

    name = "vocab-onehot"

    def __init__(self, vocab: Sequence[str], extra_dims: int = 0) -> None:
        self.vocab = list(dict.fromkeys(vocab))
        self.pos = {t: i for i, t in enumerate(self.vocab)}
        self.dim = len(self.vocab) + extra_dims
        self.calls = 0

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        self.calls += 1
        out = np.zeros((len(texts), self.dim), np.float32)
        for r, t in enumerate(texts):
            out[r, self.pos[t]] = 1.0
        return out

    def mix(self, weights: dict[str, float]) -> np.ndarray:
        """A unit feature whose cosine with text t is proportional to weights[t]."""
        v = np.zeros(self.dim, np.float32)
        for t, w in weights.items():
            v[self.pos[t]] = w
        return v / np.linalg.norm(v)


def block(origin: Sequence[float], shape: Sequence[int], spacing: float = 0.02) -> np.ndarray:
    """A filled lattice of ``shape`` points starting 0.005 m past ``origin``."""
    axes = [origin[d] + 0.005 + spacing * np.arange(shape[d]) for d in range(3)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([a.reshape(-1) for a in g], axis=1)


def sample(oid: int, synonyms: Sequence[str], depictions: Sequence[str] = (), vis_sim: Sequence[str] = (),
           clutter: Sequence[int] = (), category: str | None = None) -> dict:
    s = {
        "object_id": oid,
        "labels": {"image_attributes": {
            "synonyms": list(synonyms), "depictions": list(depictions),
            "vis_sim": list(vis_sim), "clutter": list(clutter),
        }},
    }
    if category is not None:
        s["category"] = category
    return s


def write_gt(root: Path, points: np.ndarray, labels: np.ndarray, samples: list[dict],
             prompts: Sequence[str], queries: dict, *, layout: str = "gt") -> Path:
    """Ground truth as ``trackgraph synth`` lays it out: files under ``root/gt``."""
    gt = root / "gt" if layout == "gt" else root
    gt.mkdir(parents=True, exist_ok=True)
    (gt / "gt_categories.json").write_text(json.dumps({"dataset": {"samples": samples}}))
    np.save(gt / "points.npy", np.asarray(points, np.float32))
    np.save(gt / "labels.npy", np.asarray(labels, np.int32))
    (gt / "prompt_list.txt").write_text("\n".join(prompts) + "\n")
    (gt / "gt_categories_query_to_object_mapping_all.json").write_text(json.dumps(queries))
    return root


def write_pred(root: Path, points: np.ndarray, index: np.ndarray, embeddings: np.ndarray) -> Path:
    return write_prediction(root, points, index, embeddings)


def concat(parts: list[tuple[np.ndarray, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Points and a label per point from (points, label) parts."""
    pts = np.concatenate([p for p, _ in parts])
    lab = np.concatenate([np.full(len(p), v, np.int64) for p, v in parts])
    return pts, lab


# ---------------------------------------------------------------------------- the scene

PROMPTS = [
    "filler a", "filler b", "filler c", "filler d",
    "chair", "seat", "stool", "table", "desk", "mug", "cup", "bowl", "striped pattern", "lamp", "wall",
]
QUERIES = {"level0": {"chair": [1], "table": [2]}}


@dataclass
class Scene:
    """The hand-built scene shared by the evaluation tests:

        id  name   points                                 labels
        1   chair  block (0,0,0) 10x10x10 = 1000          syn chair, seat; vis_sim stool; clutter [2]
        2   table  top (1,0,0) 10x10x2 = 200              syn table; vis_sim desk; clutter [1, 3]
                   + leg (1.5,0,0) 2x2x10 = 40 (0.3 m away)
        3   mug    block (2,0,0) 5x5x5 = 125              syn mug, cup; dep striped pattern; vis_sim bowl; clutter [2]
        4   lamp   block (3,0,0) 5x5x5 = 125              syn lamp
        9   wall   slab (0,1,0) 10x1x10 = 100             syn wall (excluded from scoring)
        7   (no entry in gt_categories.json)  block (4,0,0) 3x3x3 = 27   (not scored)
        -1  unlabelled  block (5,5,5) 2x2x2 = 8                          (not scored)
    """

    points: np.ndarray
    labels: np.ndarray
    parts: dict[str, np.ndarray]
    samples: list[dict]
    encoder: VocabEncoder

    def write(self, root: Path, queries: dict | None = None, **kw) -> Path:
        return write_gt(root, self.points, self.labels, self.samples, PROMPTS, QUERIES if queries is None else queries, **kw)


def make_scene() -> Scene:
    parts = {
        "chair": block((0, 0, 0), (10, 10, 10)),
        "table_top": block((1, 0, 0), (10, 10, 2)),
        "table_leg": block((1.5, 0, 0), (2, 2, 10)),
        "mug": block((2, 0, 0), (5, 5, 5)),
        "lamp": block((3, 0, 0), (5, 5, 5)),
        "wall": block((0, 1, 0), (10, 1, 10)),
        "unknown": block((4, 0, 0), (3, 3, 3)),
        "unlabelled": block((5, 5, 5), (2, 2, 2)),
    }
    ids = {"chair": 1, "table_top": 2, "table_leg": 2, "mug": 3, "lamp": 4, "wall": 9, "unknown": 7, "unlabelled": -1}
    points, labels = concat([(parts[k], ids[k]) for k in parts])
    samples = [
        sample(1, ["chair", "seat"], vis_sim=["stool"], clutter=[2], category="chair"),
        sample(2, ["table"], vis_sim=["desk"], clutter=[1, 3], category="table"),
        sample(3, ["mug", "cup"], depictions=["striped pattern"], vis_sim=["bowl"], clutter=[2], category="mug"),
        sample(4, ["lamp"], category="lamp"),
        sample(9, ["wall"], category="wall"),
    ]
    return Scene(points, labels, parts, samples, VocabEncoder(PROMPTS))
