"""A method's output for one scene in the OpenLex3D prediction format, loaded and checked.

``MAP_DIR/point_cloud.pcd`` (points in the ground-truth world frame; ``point_cloud.ply`` is
accepted too), ``MAP_DIR/embeddings.npy`` (n_objects x D features) and ``MAP_DIR/index.npy``
(one row of ``embeddings`` per point). Dense methods use ``index = arange(n_points)``.
"""

from __future__ import annotations

import io
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from shared.eval.errors import EvalInputError
from shared.eval.gt import GroundTruth
from shared.eval.text import TextEncoder, encode_texts, unit_rows
from shared.io import atomic_write_bytes

log = logging.getLogger(__name__)

CLOUD_FILES = ("point_cloud.pcd", "point_cloud.ply")
EMBEDDINGS_FILE = "embeddings.npy"
INDEX_FILE = "index.npy"


@dataclass
class Prediction:
    """Points with one instance row each, and one feature per instance."""

    points: Annotated[np.ndarray, "(M, 3) float64"]
    index: Annotated[np.ndarray, "(M,) int64 in [0, K)"]
    embeddings: Annotated[np.ndarray, "(K, D) float32"]
    root: Path | None = None

    @property
    def n_instances(self) -> int:
        return int(self.embeddings.shape[0])

    @property
    def dim(self) -> int:
        return int(self.embeddings.shape[1])

    def file(self, name: str) -> Path:
        """Path of one of its files, for error messages (``<oracle>/name`` when in memory)."""
        return (self.root if self.root is not None else Path("<in-memory prediction>")) / name


def _pcd_declared_points(path: Path) -> int | None:
    """The POINTS count in a PCD header (None when it is not a PCD or has no such line)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return None
    m = re.search(rb"^POINTS\s+(\d+)", head, flags=re.MULTILINE)
    return int(m.group(1)) if m else None


def read_cloud(path: Path) -> Annotated[np.ndarray, "(M, 3) float64"]:
    """Points of a .pcd or .ply file, read with Open3D's tensor reader (which, unlike the
    legacy one, reads float64 PCDs correctly)."""
    from shared.o3d import import_open3d

    o3d = import_open3d()
    if path.stat().st_size == 0:
        raise EvalInputError(path, "empty file")
    declared = _pcd_declared_points(path) if path.suffix == ".pcd" else None
    if path.suffix == ".pcd" and declared is None:
        raise EvalInputError(path, "not a PCD file (no POINTS line in its header)")
    if declared == 0:
        return np.zeros((0, 3))
    try:
        cloud = o3d.t.io.read_point_cloud(str(path))
    except (RuntimeError, OSError, ValueError) as exc:
        raise EvalInputError(path, f"Open3D cannot read it ({exc})") from exc
    if "positions" not in cloud.point:
        raise EvalInputError(path, "Open3D read no points from it (corrupt or unsupported file)")
    pts = cloud.point.positions.numpy().astype(np.float64).reshape(-1, 3)
    if declared is not None and declared != len(pts):
        raise EvalInputError(path, f"header declares {declared} points but Open3D read {len(pts)} (corrupt file?)")
    return pts


def write_cloud(path: str | Path, points: Annotated[np.ndarray, "(M, 3) float"]) -> Path:
    """A binary float32 PCD with x, y, z (Open3D cannot write an empty one; this can, and
    float32 is what OpenLex3D's legacy Open3D reader needs)."""
    pts = np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3))
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
        f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {len(pts)}\nDATA binary\n"
    )
    return atomic_write_bytes(Path(path), header.encode("ascii") + pts.astype("<f4").tobytes())


def write_prediction(
    map_dir: str | Path,
    points: Annotated[np.ndarray, "(M, 3) float"],
    index: Annotated[np.ndarray, "(M,) int in [0, K)"],
    embeddings: Annotated[np.ndarray, "(K, D) float"],
) -> Path:
    """Write a prediction folder in the OpenLex3D format (checked like :func:`load_prediction`)."""
    map_dir = Path(map_dir)
    points, index, embeddings = np.asarray(points), np.asarray(index), np.asarray(embeddings)
    if points.reshape(-1, 3).shape[0] != len(index):
        raise ValueError(f"{len(index)} index entries for {points.reshape(-1, 3).shape[0]} points")
    if len(index) and (index.min() < 0 or index.max() >= len(embeddings)):
        raise ValueError(f"index values must be in [0, {len(embeddings)})")
    map_dir.mkdir(parents=True, exist_ok=True)
    write_cloud(map_dir / CLOUD_FILES[0], points)
    for name, arr in ((EMBEDDINGS_FILE, embeddings.astype(np.float32)), (INDEX_FILE, index.astype(np.int64))):
        buf = io.BytesIO()
        np.save(buf, arr)
        atomic_write_bytes(map_dir / name, buf.getvalue())
    return map_dir


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise EvalInputError(path, f"not a readable .npy array ({exc})") from exc


def load_prediction(map_dir: str | Path) -> Prediction:
    """Load and check a prediction folder; every error names the file at fault."""
    map_dir = Path(map_dir)
    if not map_dir.is_dir():
        raise EvalInputError(map_dir, "prediction folder does not exist")
    cloud_path = next((map_dir / n for n in CLOUD_FILES if (map_dir / n).is_file()), None)
    if cloud_path is None:
        raise EvalInputError(map_dir / CLOUD_FILES[0], "missing prediction point cloud")
    emb_path, idx_path = map_dir / EMBEDDINGS_FILE, map_dir / INDEX_FILE
    for p in (emb_path, idx_path):
        if not p.is_file():
            raise EvalInputError(p, "missing prediction file")

    points = read_cloud(cloud_path)
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise EvalInputError(cloud_path, f"{bad} points are NaN or infinite")

    emb = _load_npy(emb_path)
    if emb.ndim == 1 and emb.size == 0:
        emb = emb.reshape(0, 0)
    if emb.ndim != 2 or emb.dtype.kind not in "fiu":
        raise EvalInputError(emb_path, f"expected a float (n_objects, D) array (got {emb.dtype} {emb.shape})")
    if not np.isfinite(emb).all():
        bad = int((~np.isfinite(emb).all(axis=1)).sum())
        raise EvalInputError(emb_path, f"{bad} of {len(emb)} feature rows contain NaN or infinite values")

    index = _load_npy(idx_path)
    if index.ndim != 1 or index.dtype.kind not in "iu":
        raise EvalInputError(idx_path, f"expected an integer (n_points,) array (got {index.dtype} {index.shape})")
    if len(index) != len(points):
        raise EvalInputError(
            idx_path, f"has {len(index)} entries but {cloud_path.name} has {len(points)} points (one entry per point)"
        )
    if len(index) and (index.min() < 0 or index.max() >= len(emb)):
        lo, hi = int(index.min()), int(index.max())
        raise EvalInputError(
            idx_path, f"values must be row numbers of {emb_path.name} in [0, {len(emb)}) (found {lo}..{hi})"
        )
    pred = Prediction(points, index.astype(np.int64), emb.astype(np.float32), map_dir)
    log.info("prediction %s: %d points, %d instances, D = %d", map_dir, len(points), pred.n_instances, pred.dim)
    return pred


def oracle_prediction(gt: GroundTruth, encoder: TextEncoder) -> Prediction:
    """The ground truth as a prediction: its labelled points, one instance per object.

    An object's feature is the normalised mean of the text embeddings of all its synonyms
    (its category when it has none; an object with neither gets a zero feature, which scores
    0 against every text). The mean, rather than the first synonym alone, is what a perfect
    open-vocabulary feature looks like: it retrieves the object by any of its names.
    """
    keep = gt.labels >= 0
    ids, index = np.unique(gt.labels[keep], return_inverse=True)
    rows: list[int] = []
    texts: list[str] = []
    for r, oid in enumerate(ids):
        obj = gt.objects.get(int(oid))
        names = (obj.synonyms or ((obj.category,) if obj.category else ())) if obj is not None else ()
        rows += [r] * len(names)
        texts += list(names)
    emb = np.zeros((len(ids), int(encoder.dim)), np.float32)
    if texts:
        unique = list(dict.fromkeys(texts))
        vecs = encode_texts(encoder, unique)
        pos = {t: i for i, t in enumerate(unique)}
        np.add.at(emb, np.asarray(rows), vecs[[pos[t] for t in texts]])
    emb = unit_rows(emb)
    log.info("oracle prediction: %d points, %d instances (%d named)", int(keep.sum()), len(ids), len(set(rows)))
    return Prediction(gt.points[keep], index.astype(np.int64), emb, None)
