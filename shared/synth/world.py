"""The whole world: floor plan, room shells, furniture and clutter, each object with an id,
a category, its label tiers and its clutter ids."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from shared.synth.config import SynthConfig
from shared.synth.furnish import furnish
from shared.synth.layout import Layout, build_layout, shell
from shared.synth.primitives import Part, world_mesh
from shared.synth.vocabulary import STRUCTURAL, LabelTiers, tiers

log = logging.getLogger(__name__)


@dataclass
class WorldObject:
    """One object instance: parts already in world coordinates."""

    id: int
    category: str
    room: str
    mount: str
    """structure, floor, flat, wall or item."""
    parts: list[Part]
    labels: LabelTiers
    support: int | None
    """Id of the object it stands on (small objects)."""
    lo: Annotated[np.ndarray, "(3,) float64"]
    hi: Annotated[np.ndarray, "(3,) float64"]

    @property
    def structural(self) -> bool:
        return self.category in STRUCTURAL


@dataclass
class World:
    layout: Layout
    objects: list[WorldObject]

    def parts(self) -> tuple[list[Part], Annotated[np.ndarray, "(P,) int32 object id per part"]]:
        parts = [p for o in self.objects for p in o.parts]
        owner = np.array([o.id for o in self.objects for _ in o.parts], np.int32)
        return parts, owner

    def categories(self) -> list[str]:
        return sorted({o.category for o in self.objects})


def _box_of(parts: list[Part]) -> tuple[np.ndarray, np.ndarray]:
    pts = np.vstack([world_mesh(p)[0] for p in parts])
    return pts.min(axis=0), pts.max(axis=0)


def clutter_ids(lo: Annotated[np.ndarray, "(N, 3)"], hi: Annotated[np.ndarray, "(N, 3)"], margin: float,
                eligible: Annotated[np.ndarray, "(N,) bool"] | None = None) -> list[list[int]]:
    """For each box, the indices of the other boxes it overlaps once both are inflated by
    ``margin``. Symmetric by construction; boxes not ``eligible`` take no part."""
    lo = np.asarray(lo, np.float64) - margin
    hi = np.asarray(hi, np.float64) + margin
    n = len(lo)
    overlap = np.all((lo[:, None, :] < hi[None, :, :]) & (lo[None, :, :] < hi[:, None, :]), axis=2)
    np.fill_diagonal(overlap, False)
    if eligible is not None:
        overlap &= eligible[:, None] & eligible[None, :]
    return [np.flatnonzero(overlap[i]).tolist() for i in range(n)]


def build_world(cfg: SynthConfig, seed: int) -> World:
    """The furnished floor plan of ``cfg`` for ``seed`` (deterministic)."""
    layout = build_layout(cfg.layout, np.random.default_rng([seed, 1]))
    objects: list[WorldObject] = []

    def add(category: str, room: str, mount: str, parts: list[Part], depictions: tuple[str, ...], support: int | None) -> int:
        lo, hi = _box_of(parts)
        oid = len(objects)
        objects.append(WorldObject(oid, category, room, mount, parts, tiers(category, depictions), support, lo, hi))
        return oid

    for room_name, template in shell(layout, np.random.default_rng([seed, 2])):
        add(template.category, room_name, "structure", template.parts, template.depictions, None)
    for k, room in enumerate(layout.rooms):
        if not room.furnished:
            continue
        placed = furnish(room, layout, cfg.furnish, cfg.camera.clearance, np.random.default_rng([seed, 3, k]))
        ids: list[int] = []
        for p in placed:
            support = ids[p.support] if p.support is not None else None
            parts = [part.moved(p.pose) for part in p.template.parts]
            ids.append(add(p.template.category, room.name, p.mount, parts, p.template.depictions, support))
    log.info("world: %d rooms, %d objects, %d categories", len(layout.rooms), len(objects), len({o.category for o in objects}))
    return World(layout, objects)


def world_clutter(world: World, margin: float, structure: bool) -> dict[int, list[int]]:
    """Clutter ids of every object (object id -> ids of the objects its box overlaps)."""
    lo = np.array([o.lo for o in world.objects])
    hi = np.array([o.hi for o in world.objects])
    eligible = None if structure else np.array([not o.structural for o in world.objects])
    lists = clutter_ids(lo, hi, margin, eligible)
    return {o.id: [world.objects[j].id for j in lists[i]] for i, o in enumerate(world.objects)}
