"""The ``simulated`` VL backend: CLIP-like features from ground truth (synthetic scenes only).

A crop's feature is the mix of its ground-truth objects' text embeddings, weighted by pixel
share, plus Gaussian noise, L2-normalised:

- **Weights are mask-weighted**: the shares are those of the keyframe's ground-truth ids under
  the mask's own pixels, not under the whole padded box.
  A mask that straddles two objects so mixes them in proportion, as a real crop of a bad mask
  would; the padding's context is left out, because with exact masks it would only blur
  every object towards its neighbours. ``crop_padding`` therefore plays no part here.
- Pixels of no object (-1) or of an object without labels weigh in as zero vectors: a mask
  that is mostly background carries a weak signal, which the noise then dominates; one with no
  labelled pixel at all gets a random direction.
- **Each object is embedded by its first synonym** (else its category), the name the
  evaluation's oracle prediction uses (``ObjectLabels.name``). The first synonym is itself in
  the prompt list, so a crop of one object is nearest to one of its own synonyms unless the
  noise pushes it past a close label. On the ``small`` synthetic preset (seed 0, ground-truth
  masks, every 6th frame) both this and the mean of all synonyms put 100% of objects nearest
  a synonym at the default noise; at ``noise_std=0.15`` the first synonym kept 97.1% of crops
  and the mean 95.3%.
- The noise is ``noise_std`` per component (so its norm is about ``noise_std * sqrt(384)``),
  seeded by ``(frame_index, mask index)``: the same keyframe gives the same features.

The ground-truth ids come from an :class:`~shared.datasets.ground_truth.InstanceSource` given at
construction (by default the sequence folder of ``keyframe_vl.vl.ground_truth``): a keyframe's
by its frame index, an image query's by its pixels (a sequence frame or a crop of one, pixel
for pixel). No message carries them. A folder source builds its image index on a background
thread as the encoder is made (about 3 ms a frame, once), so the first image query does not
wait for it.

A keyframe's **view** (:meth:`SimulatedVLEncoder.encode_view`, the whole frame, for naming the
room the camera is in) stands in for CLIP's whole-image embedding of a room, which lies near
the room's type (a photo of a bedroom is near "bedroom"). The synthetic world knows where
each object is: every sample of ``gt_categories.json`` has a ``room`` key (a room name), and
the rooms' types come from ``rooms.json`` beside it, or for older sequences ``scene.json``'s
room kinds (:func:`shared.eval.rooms.load_gt_rooms`). Each pixel's object gives its room and
the room its type label ("dining room", ...); the view is the pixel-share-weighted mix of
those labels' text embeddings plus noise seeded by ``(2, frame_index)``, L2-normalised.
Pixels of no object, or of an object with no room, weigh zero; a frame with no such pixel
gets a random direction, as a crop with no labelled pixel does. A sequence with no room
information (no room file, or no ``room`` keys) still gets views: the mix of the frame's
objects over all its pixels, as an image query's, said once in the log. A room file that is
there but malformed is an error naming the file and the field, at construction.

Text goes through the same offline MiniLM encoder (:class:`shared.text.minilm.MiniLMTextEncoder`),
so queries, crops and views share one 384-d space.
"""

from __future__ import annotations

import json
import logging
import zlib
from pathlib import Path
from typing import Annotated, Any, Protocol

import numpy as np

from shared.datasets.ground_truth import GroundTruthError, InstanceSource, SequenceGroundTruth
from shared.perception import KeyframeImage, Masks
from shared.perception.encoders.common import check_rgb, unit_rows
from shared.perception.encoders.crops import mask_box

log = logging.getLogger(__name__)

CATEGORIES_FILE = "gt_categories.json"
ROOM_KEY = "room"
"""The key of a ``gt_categories.json`` sample naming the room its object stands in."""
NAME = "simulated:all-MiniLM-L6-v2"
WARMUP_TEXT = "a warm-up sentence"
"""What :meth:`SimulatedVLEncoder.warm_up` embeds when its text encoder has no warm-up of its own."""
_SEED_TAG = 0x51A7C11F
"""Keeps this backend's noise streams apart from other seeded simulations."""


class TextEmbedder(Protocol):
    dim: int

    def encode(self, texts: list[str]) -> Annotated[np.ndarray, "(N, dim) float32"]: ...


def find_categories(ground_truth: str | Path | None) -> Path:
    """``gt_categories.json`` in ``ground_truth`` or in its ``gt/`` subfolder."""
    if ground_truth is None or str(ground_truth).strip() == "":
        raise ValueError(
            "the simulated VL encoder needs keyframe_vl.vl.ground_truth: a synthetic sequence folder "
            "(`trackgraph synth` writes one; `trackgraph map`, `launch` and `serve --sequence` set it when unset)"
        )
    root = Path(ground_truth).expanduser()
    for cand in (root / CATEGORIES_FILE, root / "gt" / CATEGORIES_FILE):
        if cand.is_file():
            return cand
    raise FileNotFoundError(
        f"{root / CATEGORIES_FILE}: missing (also looked for {root / 'gt' / CATEGORIES_FILE}); "
        "the simulated VL encoder needs the ground truth of a synthetic sequence (`trackgraph synth`)"
    )


def _read_categories(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not readable ground-truth categories ({exc})") from exc


def load_object_names(path: Path, data: Any = None) -> dict[int, str]:
    """Object id -> the name its embedding is made from (first synonym, else category).
    ``data`` is the file's parsed content when the caller has read it already."""
    from shared.eval.gt import parse_categories

    objects = parse_categories(_read_categories(path) if data is None else data, path)
    names = {oid: name for oid, o in objects.items() if (name := o.name())}
    if not names:
        raise ValueError(f"{path}: no object has a synonym or a category to embed")
    return names


def load_object_rooms(path: Path, data: Any = None) -> dict[int, str]:
    """Object id -> the name of the room it stands in (``dataset.samples[*].room``), for the
    objects that have one; empty for categories written without rooms."""
    if data is None:
        data = _read_categories(path)
    try:
        samples = data["dataset"]["samples"]
    except (TypeError, KeyError):
        raise ValueError(f'{path}: expected {{"dataset": {{"samples": [...]}}}}') from None
    rooms: dict[int, str] = {}
    for i, sample in enumerate(samples if isinstance(samples, list) else []):
        if not isinstance(sample, dict) or sample.get(ROOM_KEY) is None:
            continue
        room, oid = sample[ROOM_KEY], sample.get("object_id")
        if not isinstance(room, str) or not room:
            raise ValueError(f"{path}: dataset.samples[{i}].{ROOM_KEY}: expected a room name, got {room!r}")
        try:
            rooms[int(oid)] = room
        except (TypeError, ValueError):
            raise ValueError(f"{path}: dataset.samples[{i}].object_id: expected an integer, got {oid!r}") from None
    return rooms


def load_room_types(folder: Path) -> dict[str, str] | None:
    """Room name -> its type label ("dining room"), from ``rooms.json`` (else ``scene.json``)
    in ``folder`` or ``folder/gt``; None when neither file is there. A file that is there but
    malformed raises, naming the file and the field."""
    from shared.eval.rooms import ROOMS_GT_FILE, SCENE_FILE, load_gt_rooms

    if not any((d / f).is_file() for d in (folder, folder / "gt") for f in (ROOMS_GT_FILE, SCENE_FILE)):
        return None
    return {r.name: r.type for r in load_gt_rooms(folder)}


class SimulatedVLEncoder:
    """Ground-truth label mixtures in MiniLM space, from a ground-truth source."""

    name = NAME

    def __init__(
        self,
        ground_truth: str | Path | None,
        noise_std: float = 0.05,
        text_encoder: TextEmbedder | None = None,
        source: InstanceSource | None = None,
    ) -> None:
        """``ground_truth`` is the sequence folder (or its ``gt/``) whose categories give the
        labels; ``source`` the instance ids, by default read from the same folder."""
        if noise_std < 0:
            raise ValueError(f"noise_std must be >= 0 (got {noise_std})")
        self.categories = find_categories(ground_truth)
        data = _read_categories(self.categories)
        names = load_object_names(self.categories, data)
        object_rooms = load_object_rooms(self.categories, data)
        room_types = load_room_types(self.categories.parent) if object_rooms else None
        if source is None:
            folder = SequenceGroundTruth(ground_truth, field="keyframe_vl.vl.ground_truth", user="simulated VL encoder")
            folder.prepare_images(background=True)
            source = folder
        self.source = source
        if text_encoder is None:
            from shared.text.minilm import MiniLMTextEncoder

            text_encoder = MiniLMTextEncoder()
        self.text = text_encoder
        self.dim = int(text_encoder.dim)
        self.noise_std = float(noise_std)
        self._ids = np.asarray(sorted(names), np.int64)
        self._emb = np.asarray(self.text.encode([names[int(i)] for i in self._ids]), np.float32)
        self._room_objects, self._room_type, self.room_types, self._type_emb = self._rooms(object_rooms, room_types)
        self._told_no_rooms = False
        log.info(
            "simulated VL encoder: %d labelled objects from %s, noise std %.3g, %s",
            len(self._ids), self.categories, self.noise_std,
            f"views from {len(self.room_types)} room types" if self.room_types else "views without room types",
        )  # fmt: skip

    def _rooms(
        self, object_rooms: dict[int, str], room_types: dict[str, str] | None
    ) -> tuple[
        Annotated[np.ndarray, "(R,) int64 sorted object ids with a typed room"],
        Annotated[np.ndarray, "(R,) int64 index into the type labels"],
        list[str],
        Annotated[np.ndarray, "(T, D) float32 unit rows"] | None,
    ]:
        """The lookup from object to its room's type label, and the labels' embeddings; empty
        (and None) when the sequence tells no object's room type."""
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), [], None)
        if not object_rooms or not room_types:
            return none
        unknown = sorted({r for r in object_rooms.values() if r not in room_types})
        if unknown:
            log.warning(
                "%s: objects stand in rooms the room ground truth does not list (%s); their pixels weigh nothing in views",
                self.categories, ", ".join(unknown),
            )  # fmt: skip
        typed = {oid: room_types[r] for oid, r in object_rooms.items() if r in room_types}
        if not typed:
            return none
        labels = sorted(set(typed.values()))
        objects = np.asarray(sorted(typed), np.int64)
        index = np.asarray([labels.index(typed[int(o)]) for o in objects], np.int64)
        return objects, index, labels, unit_rows(self.text.encode(labels))

    def _mix(self, ids: Annotated[np.ndarray, "(P,) int"]) -> Annotated[np.ndarray, "(D,) float32"]:
        """Pixel-share-weighted sum of the embeddings of the objects among ``ids``."""
        if ids.size == 0:
            return np.zeros(self.dim, np.float32)
        values, counts = np.unique(ids, return_counts=True)
        pos = np.clip(np.searchsorted(self._ids, values), 0, len(self._ids) - 1)
        known = self._ids[pos] == values
        shares = counts[known].astype(np.float32) / np.float32(ids.size)
        return shares @ self._emb[pos[known]]

    def _finish(self, mix: np.ndarray, key: tuple[int, ...]) -> Annotated[np.ndarray, "(D,) float32"]:
        rng = np.random.default_rng((_SEED_TAG, *key))
        noise = rng.standard_normal(self.dim).astype(np.float32)
        if not np.any(mix):
            return unit_rows(noise[None])[0]
        return unit_rows((mix + np.float32(self.noise_std) * noise)[None])[0]

    def _room_mix(self, ids: Annotated[np.ndarray, "(P,) int"]) -> Annotated[np.ndarray, "(D,) float32"]:
        """Pixel-share-weighted sum of the embeddings of the room types of the objects among
        ``ids`` (pixels of no object, or of an object without a typed room, weigh zero)."""
        assert self._type_emb is not None
        if ids.size == 0:
            return np.zeros(self.dim, np.float32)
        values, counts = np.unique(ids, return_counts=True)
        pos = np.clip(np.searchsorted(self._room_objects, values), 0, len(self._room_objects) - 1)
        known = self._room_objects[pos] == values
        per_type = np.bincount(self._room_type[pos[known]], weights=counts[known], minlength=len(self.room_types))
        return (per_type / ids.size).astype(np.float32) @ self._type_emb

    def _keyframe_instances(self, image: KeyframeImage) -> Annotated[np.ndarray, "(H, W) int object ids, -1 none"]:
        """The ground-truth ids of keyframe ``image.frame_index``, checked against its size."""
        rgb = check_rgb(image.rgb)
        try:
            inst = np.asarray(self.source.frame_instances(image.frame_index))
        except GroundTruthError as exc:
            raise GroundTruthError(f"keyframe {image.frame_index}: the simulated VL encoder has no ground truth: {exc}") from None
        if inst.shape != rgb.shape[:2]:
            raise GroundTruthError(
                f"keyframe {image.frame_index}: the ground-truth instances are {inst.shape[1]}x{inst.shape[0]} but the image is "
                f"{rgb.shape[1]}x{rgb.shape[0]}: is keyframe_vl.vl.ground_truth the sequence being replayed?"
            )
        return inst

    def encode_crops(self, image: KeyframeImage, masks: Masks) -> Annotated[np.ndarray, "(N, 384) float32"]:
        """One feature per mask: its pixels' ground-truth mix plus noise seeded by
        ``(frame_index, mask index)``."""
        inst = self._keyframe_instances(image)
        rgb = image.rgb
        if masks.masks.shape[1:] != rgb.shape[:2]:
            raise ValueError(f"masks of shape {masks.masks.shape} do not match the image {rgb.shape[:2]}")
        out = np.zeros((len(masks), self.dim), np.float32)
        for j, mask in enumerate(masks.masks):
            box = mask_box(mask)
            if box is None:
                ids = np.zeros(0, np.int64)
            else:
                x0, y0, x1, y1 = box
                ids = inst[y0:y1, x0:x1][mask[y0:y1, x0:x1]]
            out[j] = self._finish(self._mix(ids), (0, int(image.frame_index), j))
        return out

    def encode_view(self, image: KeyframeImage) -> Annotated[np.ndarray, "(384,) float32"]:
        """The whole keyframe: the mix of the room types under its pixels (see the module
        docstring) plus noise seeded by ``(2, frame_index)``; without room ground truth, the
        mix of its objects."""
        inst = self._keyframe_instances(image).ravel()
        if self._type_emb is not None:
            mix = self._room_mix(inst)
        else:
            if not self._told_no_rooms:
                self._told_no_rooms = True
                log.info(
                    "%s: no object has a room of known type (no rooms.json or scene.json rooms, or no %r keys): "
                    "keyframe views carry no room type, only the mix of the frame's objects",
                    self.categories, ROOM_KEY,
                )  # fmt: skip
            mix = self._mix(inst)
        return self._finish(mix, (2, int(image.frame_index)))

    def warm_up(self) -> None:
        """Load the text model now: the labels' embeddings usually come from the disk cache,
        so without this the first novel query text would wait for the load."""
        warm = getattr(self.text, "warm_up", None)
        if warm is not None:
            warm()
        else:
            self.text.encode([WARMUP_TEXT])

    def encode_text(self, texts: list[str]) -> Annotated[np.ndarray, "(N, 384) float32"]:
        texts = [str(t) for t in texts]
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        return unit_rows(self.text.encode(texts))

    def encode_image(self, rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]) -> Annotated[np.ndarray, "(384,) float32"]:
        """The mix of the ground-truth ids under the image, which must be a frame of the
        sequence or a crop of one. The noise is seeded by the ids' bytes, so the same image
        query gives the same feature."""
        rgb = check_rgb(rgb)
        try:
            inst = np.ascontiguousarray(self.source.image_instances(rgb))
        except GroundTruthError as exc:
            raise GroundTruthError(f"the simulated VL encoder has no ground truth for this image: {exc}") from None
        return self._finish(self._mix(inst.ravel()), (1, zlib.crc32(inst.tobytes())))
