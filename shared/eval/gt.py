"""Ground truth of one scene in the OpenLex3D layout, loaded and checked.

Files (each looked for in ``GT_DIR`` and in ``GT_DIR/gt``, so either the sequence folder
written by ``trackgraph synth`` or its ``gt/`` subfolder can be passed):

- ``gt_categories.json``: ``{"dataset": {"samples": [{"object_id": int, "category" or
  "name": str (optional), "labels": {"image_attributes": {"synonyms": [...], "depictions":
  [...], "vis_sim": [...], "clutter": [object ids, as ints or strings]}}}]}}`` (the OpenLex3D
  format; a missing tier is an empty list);
- ``points.npy``: float (N, 3) labelled point cloud in the world frame;
- ``labels.npy``: int (N,) object id of each point (negative: no object);
- ``prompt_list.txt``: the dataset's label vocabulary, one prompt a line;
- ``gt_categories_query_to_object_mapping_all.json`` (or the one
  ``gt_categories_query_to_object_mapping_*.json`` present): ``{level: {query text: [object
  ids]}}`` as OpenLex3D writes it, or a flat ``{query text: [object ids]}``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from shared.eval.errors import EvalInputError

log = logging.getLogger(__name__)

CATEGORIES_FILE = "gt_categories.json"
POINTS_FILE = "points.npy"
LABELS_FILE = "labels.npy"
PROMPTS_FILE = "prompt_list.txt"
QUERIES_FILE = "gt_categories_query_to_object_mapping_all.json"
QUERIES_GLOB = "gt_categories_query_to_object_mapping_*.json"

TIERS = ("synonyms", "depictions", "vis_sim")
"""The label tiers of an object, in the order a label is matched against them."""

EXCLUDED_LABELS = ("wall", "floor", "ceiling", "doorframe", "ledge", "window ledge")
"""Objects with one of these among their synonyms (or as their category) are not evaluated
(OpenLex3D's ``excluded_labels``)."""


def strip_label(label: str) -> str:
    """Labels are compared with spaces removed, as OpenLex3D does ("tv stand" == "tvstand")."""
    return str(label).replace(" ", "")


@dataclass(frozen=True)
class ObjectLabels:
    """The OpenLex3D labels of one ground-truth object."""

    object_id: int
    category: str | None
    synonyms: tuple[str, ...]
    depictions: tuple[str, ...] = ()
    vis_sim: tuple[str, ...] = ()
    clutter: tuple[int, ...] = ()

    def tier(self, name: str) -> tuple[str, ...]:
        return getattr(self, name)

    def name(self) -> str | None:
        """First synonym, else the category."""
        if self.synonyms:
            return self.synonyms[0]
        return self.category

    def is_excluded(self, excluded: Iterable[str] = EXCLUDED_LABELS) -> bool:
        names = {strip_label(s) for s in self.synonyms}
        if self.category:
            names.add(strip_label(self.category))
        return any(strip_label(e) in names for e in excluded)


@dataclass(frozen=True)
class Query:
    """One retrieval query: its text and the ground-truth objects it should find."""

    query_id: str
    text: str
    object_ids: tuple[int, ...]
    level: str | None = None


@dataclass
class GroundTruth:
    """A scene's labelled point cloud, object labels, prompt list and queries."""

    root: Path
    points: Annotated[np.ndarray, "(N, 3) float64"]
    labels: Annotated[np.ndarray, "(N,) int64 object id, negative = none"]
    objects: dict[int, ObjectLabels]
    prompts: list[str]
    queries: list[Query]
    files: dict[str, Path] = field(default_factory=dict)

    def evaluated_object_ids(self, excluded: Iterable[str] = EXCLUDED_LABELS) -> np.ndarray:
        """Sorted ids of the objects that are scored: present in the point cloud, labelled
        with at least one synonym, and not structure (wall, floor, ...)."""
        excluded = tuple(excluded)
        present = np.unique(self.labels[self.labels >= 0])
        keep = [
            int(i)
            for i in present
            if (o := self.objects.get(int(i))) is not None and o.synonyms and not o.is_excluded(excluded)
        ]
        return np.asarray(keep, dtype=np.int64)

    def object_rows(self, object_ids: Annotated[np.ndarray, "(O,) sorted int"]) -> Annotated[np.ndarray, "(N,) int64"]:
        """Each point's position in ``object_ids`` (-1 for points of other objects or none)."""
        if len(object_ids) == 0:
            return np.full(len(self.labels), -1, np.int64)
        pos = np.minimum(np.searchsorted(object_ids, self.labels), len(object_ids) - 1)
        return np.where(object_ids[pos] == self.labels, pos, -1).astype(np.int64)


def _find(gt_dir: Path, name: str) -> Path:
    for cand in (gt_dir / name, gt_dir / "gt" / name):
        if cand.is_file():
            return cand
    raise EvalInputError(gt_dir / "gt" / name, f"missing ground-truth file {name} (looked in {gt_dir} and {gt_dir / 'gt'})")


def _find_queries(gt_dir: Path) -> Path:
    for folder in (gt_dir, gt_dir / "gt"):
        if (folder / QUERIES_FILE).is_file():
            return folder / QUERIES_FILE
    found = sorted({*gt_dir.glob(QUERIES_GLOB), *(gt_dir / "gt").glob(QUERIES_GLOB)})
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        raise EvalInputError(
            gt_dir / "gt" / QUERIES_FILE,
            f"missing; found several query mappings ({', '.join(p.name for p in found)}) and cannot choose",
        )
    raise EvalInputError(gt_dir / "gt" / QUERIES_FILE, "missing ground-truth query mapping")


def _read_json(path: Path) -> Any:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as exc:
        raise EvalInputError(path, f"not valid JSON ({exc})") from exc
    except OSError as exc:
        raise EvalInputError(path, f"cannot read ({exc.strerror or exc})") from exc


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise EvalInputError(path, f"not a readable .npy array ({exc})") from exc


def _int_id(value: Any, path: Path, what: str) -> int:
    if isinstance(value, bool):
        raise EvalInputError(path, f"{what} must be an integer (got {value!r})")
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str) and value.strip().lstrip("-").isdigit():
        return int(value.strip())
    raise EvalInputError(path, f"{what} must be an integer (got {value!r})")


def _labels_list(value: Any, path: Path, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise EvalInputError(path, f"{where} must be a list of strings")
    return tuple(value)


def parse_categories(data: Any, path: Path) -> dict[int, ObjectLabels]:
    """Object labels from the parsed ``gt_categories.json``."""
    try:
        samples = data["dataset"]["samples"]
    except (TypeError, KeyError) as exc:
        raise EvalInputError(path, 'expected {"dataset": {"samples": [...]}}') from exc
    if not isinstance(samples, list):
        raise EvalInputError(path, "dataset.samples must be a list")
    objects: dict[int, ObjectLabels] = {}
    for i, sample in enumerate(samples):
        where = f"dataset.samples[{i}]"
        if not isinstance(sample, dict) or "object_id" not in sample:
            raise EvalInputError(path, f"{where} has no object_id")
        oid = _int_id(sample["object_id"], path, f"{where}.object_id")
        labels = sample.get("labels") or {}
        attrs = labels.get("image_attributes", labels) if isinstance(labels, dict) else None
        if not isinstance(attrs, dict):
            raise EvalInputError(path, f"{where}.labels.image_attributes must be an object")
        tiers = {t: _labels_list(attrs.get(t), path, f"{where}.labels.image_attributes.{t}") for t in TIERS}
        clutter_raw = attrs.get("clutter") or []
        if not isinstance(clutter_raw, list):
            raise EvalInputError(path, f"{where}.labels.image_attributes.clutter must be a list of object ids")
        clutter = tuple(_int_id(c, path, f"{where}.labels.image_attributes.clutter") for c in clutter_raw)
        category = sample.get("category", sample.get("name"))
        if category is not None and not isinstance(category, str):
            raise EvalInputError(path, f"{where}.category must be a string")
        if oid in objects:
            raise EvalInputError(path, f"{where}: object_id {oid} appears twice")
        objects[oid] = ObjectLabels(oid, category, tiers["synonyms"], tiers["depictions"], tiers["vis_sim"], clutter)
    return objects


def parse_queries(data: Any, path: Path) -> list[Query]:
    """Queries from a parsed query mapping, nested by level or flat."""
    if not isinstance(data, dict):
        raise EvalInputError(path, "expected an object mapping query text (or level) to object ids")
    nested = bool(data) and all(isinstance(v, dict) for v in data.values())
    groups = data.items() if nested else [(None, data)]
    queries: list[Query] = []
    for level, mapping in groups:
        for text, ids in mapping.items():
            if not isinstance(ids, list):
                raise EvalInputError(path, f"query {text!r}: expected a list of object ids (got {type(ids).__name__})")
            oids = tuple(dict.fromkeys(_int_id(v, path, f"query {text!r} object id") for v in ids))
            qid = f"{level}_{text}" if level is not None else str(text)
            queries.append(Query(qid, str(text), oids, level))
    return queries


def read_prompts(path: Path) -> list[str]:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise EvalInputError(path, f"cannot read ({exc})") from exc
    prompts = list(dict.fromkeys(s.strip() for s in lines if s.strip()))
    if not prompts:
        raise EvalInputError(path, "the prompt list is empty")
    return prompts


def load_gt(gt_dir: str | Path) -> GroundTruth:
    """Load and check a scene's ground truth; every error names the file at fault."""
    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise EvalInputError(gt_dir, "ground-truth folder does not exist")
    files = {
        "categories": _find(gt_dir, CATEGORIES_FILE),
        "points": _find(gt_dir, POINTS_FILE),
        "labels": _find(gt_dir, LABELS_FILE),
        "prompts": _find(gt_dir, PROMPTS_FILE),
        "queries": _find_queries(gt_dir),
    }
    points = _load_npy(files["points"])
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind not in "fiu":
        raise EvalInputError(files["points"], f"expected a float (N, 3) array (got {points.dtype} {points.shape})")
    points = points.astype(np.float64)
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise EvalInputError(files["points"], f"{bad} points are NaN or infinite")
    labels = _load_npy(files["labels"])
    if labels.ndim != 1 or labels.dtype.kind not in "iu":
        raise EvalInputError(files["labels"], f"expected an integer (N,) array (got {labels.dtype} {labels.shape})")
    if len(labels) != len(points):
        raise EvalInputError(
            files["labels"], f"has {len(labels)} labels but {files['points'].name} has {len(points)} points"
        )
    objects = parse_categories(_read_json(files["categories"]), files["categories"])
    prompts = read_prompts(files["prompts"])
    queries = parse_queries(_read_json(files["queries"]), files["queries"])
    gt = GroundTruth(gt_dir, points, labels.astype(np.int64), objects, prompts, queries, files)
    log.info(
        "ground truth %s: %d points, %d labelled objects (%d scored), %d prompts, %d queries",
        gt_dir, len(points), len(objects), len(gt.evaluated_object_ids()), len(prompts), len(queries),
    )
    return gt
