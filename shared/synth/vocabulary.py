"""Categories and their OpenLex3D label tiers.

OpenLex3D gives each object three tiers of acceptable labels: *synonyms* (what the object is),
*depictions* (what is printed or shown on it, e.g. the subject of a picture or the pattern of
a cushion) and *vis_sim* (visually similar categories a careful person could confuse it with).
This table is static per category; patterns and picture subjects chosen per instance add
depictions on top (see :data:`PATTERN_DEPICTIONS` and :data:`MOTIF_DEPICTIONS`).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LabelTiers:
    """The three label tiers of one category."""

    synonyms: tuple[str, ...]
    depictions: tuple[str, ...] = ()
    vis_sim: tuple[str, ...] = ()


STRUCTURAL = ("wall", "floor", "ceiling")
"""Categories of the room shell; OpenLex3D's evaluation excludes them by name."""

VOCABULARY: dict[str, LabelTiers] = {
    "wall": LabelTiers(("wall",), (), ("partition",)),
    "floor": LabelTiers(("floor", "flooring"), (), ("ground",)),
    "ceiling": LabelTiers(("ceiling",), (), ("roof",)),
    "chair": LabelTiers(("chair", "dining chair", "seat"), (), ("stool", "armchair", "office chair")),
    "stool": LabelTiers(("stool", "bar stool", "seat"), (), ("chair", "side table")),
    "armchair": LabelTiers(("armchair", "lounge chair", "easy chair"), (), ("sofa", "chair", "couch")),
    "sofa": LabelTiers(("sofa", "couch", "settee"), (), ("armchair", "bed", "bench")),
    "office chair": LabelTiers(("office chair", "desk chair", "swivel chair", "chair"), (), ("armchair", "stool")),
    "table": LabelTiers(("table", "dining table", "kitchen table"), (), ("desk", "coffee table", "counter")),
    "coffee table": LabelTiers(("coffee table", "low table", "table"), (), ("side table", "bench", "nightstand")),
    "desk": LabelTiers(("desk", "writing desk", "work desk"), (), ("table", "counter")),
    "bed": LabelTiers(("bed", "double bed", "mattress"), ("blanket", "duvet"), ("sofa", "couch")),
    "pillow": LabelTiers(("pillow", "bed pillow"), (), ("cushion", "blanket")),
    "cushion": LabelTiers(("cushion", "throw pillow", "sofa pillow"), (), ("pillow", "blanket")),
    "bookshelf": LabelTiers(("bookshelf", "bookcase", "shelf", "shelving unit"), ("books",), ("cabinet", "cupboard")),
    "cabinet": LabelTiers(("cabinet", "cupboard", "sideboard"), (), ("drawer", "dresser", "wardrobe", "nightstand")),
    "wardrobe": LabelTiers(("wardrobe", "closet", "armoire"), (), ("cabinet", "cupboard", "door")),
    "nightstand": LabelTiers(("nightstand", "bedside table", "night table"), (), ("cabinet", "drawer", "side table")),
    "tv stand": LabelTiers(("tv stand", "media console", "tv cabinet"), (), ("cabinet", "sideboard", "shelf")),
    "tv": LabelTiers(("tv", "television", "tv screen"), ("black screen",), ("monitor", "screen", "picture frame")),
    "monitor": LabelTiers(("monitor", "computer monitor", "computer screen"), (), ("tv", "screen", "laptop")),
    "keyboard": LabelTiers(("keyboard", "computer keyboard"), ("keys",), ("laptop", "tray")),
    "laptop": LabelTiers(("laptop", "notebook computer", "computer"), (), ("monitor", "keyboard", "book")),
    "table lamp": LabelTiers(("table lamp", "lamp", "desk lamp", "light"), (), ("vase", "floor lamp")),
    "floor lamp": LabelTiers(("floor lamp", "lamp", "standing lamp", "light"), (), ("table lamp", "coat rack")),
    "potted plant": LabelTiers(("potted plant", "plant", "house plant", "flower pot"), ("leaves",), ("vase", "flowers")),
    "vase": LabelTiers(("vase", "jar"), (), ("bottle", "flower pot", "urn")),
    "bottle": LabelTiers(("bottle", "water bottle", "glass bottle"), (), ("vase", "can", "jar")),
    "mug": LabelTiers(("mug", "cup", "coffee mug"), (), ("glass", "jar", "bowl")),
    "bowl": LabelTiers(("bowl", "dish"), (), ("plate", "basket", "pot")),
    "book": LabelTiers(("book", "books", "novel"), ("text",), ("notebook", "magazine", "box")),
    "box": LabelTiers(("box", "cardboard box", "storage box"), (), ("bin", "basket", "book")),
    "clock": LabelTiers(("clock", "wall clock"), ("numbers", "clock hands"), ("plate", "mirror")),
    "picture frame": LabelTiers(("picture frame", "picture", "painting", "wall art", "frame"), (), ("poster", "mirror", "tv", "window")),
    "rug": LabelTiers(("rug", "carpet", "mat"), (), ("blanket", "floor", "towel")),
    "trash bin": LabelTiers(("trash bin", "trash can", "garbage bin", "waste basket"), (), ("bucket", "vase", "basket")),
    "whiteboard": LabelTiers(("whiteboard", "white board", "dry erase board"), (), ("picture frame", "screen", "poster")),
    "radiator": LabelTiers(("radiator", "heater"), (), ("vent", "shelf", "grill")),
}
"""Label tiers of every category the generator can place, the room shell included."""

PATTERN_DEPICTIONS: dict[str, tuple[str, ...]] = {
    "stripes": ("stripes", "striped pattern"),
    "checker": ("checkered pattern", "plaid"),
}
"""Depictions added to an object whose fabric carries one of these patterns."""

MOTIF_DEPICTIONS: dict[str, tuple[str, ...]] = {
    "mountains": ("mountains", "landscape", "snow"),
    "sea": ("sea", "ocean", "sunset"),
    "flowers": ("flowers", "meadow"),
    "abstract": ("abstract art", "shapes"),
}
"""Depictions of a picture frame by the subject painted on its canvas."""


def tiers(category: str, extra_depictions: tuple[str, ...] = ()) -> LabelTiers:
    """The label tiers of one object: its category's, plus depictions of its own pattern."""
    base = VOCABULARY[category]
    deps = tuple(dict.fromkeys(base.depictions + tuple(extra_depictions)))
    return LabelTiers(base.synonyms, deps, base.vis_sim)


def prompt_list() -> list[str]:
    """Every label of every tier of every category, deduplicated and sorted.

    It is the dataset-wide prompt list (OpenLex3D ranks each point's 5 best prompts of the
    whole dataset's list), so it does not depend on which objects a given seed places.
    """
    labels: set[str] = set()
    for t in VOCABULARY.values():
        labels.update(t.synonyms, t.depictions, t.vis_sim)
    for extra in (*PATTERN_DEPICTIONS.values(), *MOTIF_DEPICTIONS.values()):
        labels.update(extra)
    return sorted(labels)
