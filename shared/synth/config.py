"""Every knob of the synthetic world generator, and the named presets."""

from __future__ import annotations

import math
import numbers
import re
from typing import Literal

from pydantic import Field, model_validator

from shared.config.base import ConfigError, StrictModel, deep_merge, validate

RoomKind = Literal["living", "bedroom", "office", "dining"]

MAX_DEPTH_UNITS = 65535
MAX_SUITE_ROOMS = 5
"""A suite is one row of rooms; longer rows belong in a ``building``."""
MAX_BUILDING_ROOMS = 24
"""Most rooms of a ``building`` (two rows of 12, a corridor of about 65 m)."""
MIN_IMAGE_SIDE = 32
MAX_IMAGE_SIDE = 4096
"""Bounds of the image width and height (pixels), for the config and ``--resolution``."""


class LayoutConfig(StrictModel):
    """Rooms, walls and doorways."""

    kind: Literal["single", "suite", "revisit", "building"] = "single"
    """single: one furnished room with a doorway to a short hall; suite: ``rooms`` furnished
    rooms in a row, joined by doorways; revisit: two furnished rooms at the two ends of a long
    corridor, and the camera comes back to the first one; building: ``rooms`` furnished rooms
    on both sides of a straight corridor, each with a doorway onto it (one floor of an office
    or apartment block), toured one after the other round the corridor."""
    rooms: int = Field(3, ge=1, le=MAX_BUILDING_ROOMS)
    """Number of furnished rooms of a ``suite`` (at most 5) or a ``building`` (the other kinds
    fix it)."""
    room_width: tuple[float, float] = (4.6, 6.0)
    """Range (min, max) of a room's extent along x between wall centre lines (m)."""
    room_depth: tuple[float, float] = (4.2, 5.2)
    """Range (min, max) of a room's extent along y between wall centre lines (m)."""
    wall_height: float = Field(2.6, ge=2.2, le=4.0)
    """Floor to ceiling (m)."""
    wall_thickness: float = Field(0.12, gt=0.02, le=0.4)
    """Thickness of every wall (m)."""
    door_width: float = Field(1.0, ge=0.8, le=2.0)
    """Width of a doorway (m); the camera passes through its middle."""
    door_height: float = Field(2.1, ge=1.9, le=3.0)
    """Height of a doorway's opening (m); a lintel fills the wall above it."""
    corridor_length: float = Field(9.0, ge=4.0, le=30.0)
    """Length of the ``revisit`` corridor between the two rooms (m)."""
    corridor_width: float = Field(1.6, ge=1.2, le=3.0)
    """Width of the corridor of a ``revisit`` or a ``building`` (m)."""
    room_kinds: list[RoomKind] | None = None
    """Furnishing style of the furnished rooms, in order; None draws them at random, without
    repeats while there are unused styles."""

    @model_validator(mode="after")
    def _ranges(self) -> LayoutConfig:
        if self.kind == "suite" and self.rooms > MAX_SUITE_ROOMS:
            raise ValueError(f"a suite has at most {MAX_SUITE_ROOMS} rooms in its row (got {self.rooms}); "
                             "kind 'building' takes more")
        for name in ("room_width", "room_depth"):
            lo, hi = getattr(self, name)
            if not 3.5 <= lo <= hi <= 12.0:
                raise ValueError(f"{name} must satisfy 3.5 <= min <= max <= 12 (got {lo}, {hi})")
        if self.door_height >= self.wall_height:
            raise ValueError("door_height must be below wall_height")
        if self.door_width > self.corridor_width - 2 * self.wall_thickness:
            raise ValueError("door_width must fit in the corridor (corridor_width - 2 wall_thickness)")
        return self


class FurnishConfig(StrictModel):
    """Furniture, clutter and the objects standing on other objects."""

    large_objects: tuple[int, int] = (8, 11)
    """Range (min, max) of floor-standing and wall-hung pieces tried per room (companions such
    as chairs around a table and nightstands beside a bed come on top)."""
    small_object_fill: float = Field(0.8, ge=0.0, le=1.0)
    """Probability that each free slot of a supporting surface (table, desk, shelf, sofa seat)
    gets a small object."""
    max_items_per_surface: int = Field(5, ge=0, le=20)
    """Most small objects placed on one surface."""
    clutter_margin: float = Field(0.02, ge=0.0, le=0.5)
    """Boxes are inflated by this (m, each side) before the overlap test giving clutter ids."""
    structure_in_clutter: bool = False
    """Whether walls, floors and ceilings take part in clutter ids (OpenLex3D excludes them
    from evaluation, and a floor overlaps every object standing on it)."""


class CameraConfig(StrictModel):
    """The pinhole camera and its walk through the rooms."""

    width: int = Field(640, ge=MIN_IMAGE_SIDE, le=MAX_IMAGE_SIDE)
    """Image width (pixels)."""
    height: int = Field(480, ge=MIN_IMAGE_SIDE, le=MAX_IMAGE_SIDE)
    """Image height (pixels)."""
    hfov_deg: float = Field(75.0, ge=30.0, le=120.0)
    """Horizontal field of view; fx = fy = (width / 2) / tan(hfov / 2) (square pixels), so the
    vertical field follows from the aspect ratio."""
    frames: int = Field(900, ge=2, le=100000)
    """Number of frames, spaced evenly along the walk."""
    eye_height: float = Field(1.5, ge=0.3, le=2.0)
    """Height of the camera above the floor (m)."""
    bob: float = Field(0.02, ge=0.0, le=0.1)
    """Amplitude of the vertical walking bob (m)."""
    pitch_deg: float = Field(-14.0, ge=-60.0, le=30.0)
    """Mean pitch (negative looks down)."""
    pitch_wobble_deg: float = Field(4.0, ge=0.0, le=20.0)
    """Amplitude of a slow pitch variation."""
    look_inward: float = Field(0.65, ge=0.0, le=1.0)
    """In open space the look direction turns this fraction of the way from the walking
    direction towards the room's centre (0: look where walking)."""
    sweep_deg: float = Field(30.0, ge=0.0, le=90.0)
    """Amplitude of the left-right look sweep in open space (it fades out in doorways)."""
    sweep_period_m: float = Field(5.0, gt=0.5, le=50.0)
    """Walked distance of one full left-right sweep (m)."""
    clearance: float = Field(0.35, ge=0.1, le=1.0)
    """Least horizontal distance between the camera and any wall or furniture (m, to within the
    5 cm planning grid); must be below half the door width."""
    smoothing: float = Field(0.35, ge=0.0, le=2.0)
    """Gaussian smoothing of the walked path (sigma, m); reduced where it would cut a corner
    closer than ``clearance``."""
    yaw_smoothing: float = Field(0.5, ge=0.0, le=3.0)
    """Gaussian smoothing of the heading along the path (sigma, m)."""
    max_yaw_step_deg: float = Field(8.0, gt=0.0, le=90.0)
    """Largest change of heading between consecutive frames (the yaw is smoothed until it
    holds)."""
    loop_scale: float = Field(0.28, ge=0.05, le=0.45)
    """A room is toured around a rectangle of this fraction of its size around its centre."""


class RenderConfig(StrictModel):
    """Shading, sensor noise and file encodings."""

    ambient: float = Field(0.4, ge=0.0, le=1.0)
    """Ambient light."""
    bounce: float = Field(0.3, ge=0.0, le=1.0)
    """Light bounced off the floor onto surfaces facing down (ceilings, undersides)."""
    sun_strength: float = Field(0.35, ge=0.0, le=2.0)
    """Strength of the two fixed directional lights."""
    lamp_strength: float = Field(0.45, ge=0.0, le=2.0)
    """Strength of the ceiling point light of each room."""
    textures: bool = True
    """Procedural textures (stripes, checker, noise, wood, pictures); off gives flat colours."""
    rgb_noise_std: float = Field(2.0, ge=0.0, le=50.0)
    """Gaussian noise on RGB (standard deviation in 0-255 units)."""
    depth_noise_std: float = Field(0.0, ge=0.0, le=0.1)
    """Gaussian depth noise (m) at 1 m; it grows with the square of the depth."""
    depth_max: float = Field(10.0, gt=0.1)
    """Readings beyond this depth (m) are written as 0 (no reading)."""
    depth_scale: float = Field(6553.5, gt=0.0)
    """Depth PNG units per metre (Replica: 6553.5)."""
    jpeg_quality: int = Field(95, ge=50, le=100)
    """JPEG quality of the RGB frames."""

    @model_validator(mode="after")
    def _depth_fits(self) -> RenderConfig:
        if self.depth_max * self.depth_scale > MAX_DEPTH_UNITS:
            raise ValueError(
                f"depth_max * depth_scale must fit in uint16 ({MAX_DEPTH_UNITS}); "
                f"got {self.depth_max} * {self.depth_scale}"
            )
        return self


class GroundTruthConfig(StrictModel):
    """The labelled ground-truth point cloud and the picture files."""

    point_spacing: float = Field(0.015, ge=0.005, le=0.1)
    """Mean spacing of points sampled on object surfaces (m)."""
    contact_sheet_frames: int = Field(4, ge=1, le=12)
    """Frames shown in contact_sheet.png."""


class SynthConfig(StrictModel):
    """A synthetic indoor RGB-D sequence with ground truth (see ``shared.synth``)."""

    layout: LayoutConfig = Field(default_factory=LayoutConfig)
    """Rooms, walls and doorways."""
    furnish: FurnishConfig = Field(default_factory=FurnishConfig)
    """Furniture and small objects."""
    camera: CameraConfig = Field(default_factory=CameraConfig)
    """Camera model and trajectory."""
    render: RenderConfig = Field(default_factory=RenderConfig)
    """Shading and encodings."""
    gt: GroundTruthConfig = Field(default_factory=GroundTruthConfig)
    """Ground truth sampling."""

    @model_validator(mode="after")
    def _camera_fits_doors(self) -> SynthConfig:
        if self.camera.clearance >= self.layout.door_width / 2 - 0.02:
            raise ValueError(
                f"camera.clearance ({self.camera.clearance}) must be below half the door width "
                f"({self.layout.door_width / 2}) or the camera cannot pass a doorway"
            )
        if self.camera.eye_height + self.camera.bob >= self.layout.wall_height - 0.1:
            raise ValueError("camera.eye_height must stay below the ceiling")
        return self

    def focal(self) -> float:
        """fx = fy from the horizontal field of view."""
        return (self.camera.width / 2) / math.tan(math.radians(self.camera.hfov_deg) / 2)


PRESETS: dict[str, dict] = {
    "small": {
        "layout": {"kind": "single"},
        "camera": {"width": 320, "height": 240, "frames": 120},
        "gt": {"point_spacing": 0.02},
    },
    "demo": {
        "layout": {"kind": "suite", "rooms": 3},
        "camera": {"width": 640, "height": 480, "frames": 900},
        "gt": {"point_spacing": 0.02},
    },
    "revisit": {
        "layout": {"kind": "revisit"},
        "camera": {"width": 640, "height": 480, "frames": 600},
        "gt": {"point_spacing": 0.02},
    },
    # Ten furnished rooms round a corridor 25-30 m long: 165-220 m walked (seeds 0-9), so 3000
    # frames are 5.5-7.5 cm apart (demo: 3-3.5 cm, revisit: 8-8.5 cm). Made to show how
    # map-update cost grows with the building, against demo at the same resolution.
    "building": {
        "layout": {"kind": "building", "rooms": 10},
        "camera": {"width": 640, "height": 480, "frames": 3000},
        "gt": {"point_spacing": 0.02},
    },
}
"""Named starting points; ``preset_config`` layers user overrides on top."""

_RESOLUTION = re.compile(r"([0-9]+)[xX]([0-9]+)")


def check_resolution(width: int, height: int) -> tuple[int, int]:
    """``(width, height)`` if both are whole numbers of pixels within the image bounds, else
    ValueError with a one-line reason."""
    for v in (width, height):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or not MIN_IMAGE_SIDE <= v <= MAX_IMAGE_SIDE:
            raise ValueError(f"expected width and height as whole numbers of pixels from {MIN_IMAGE_SIDE} to "
                             f"{MAX_IMAGE_SIDE} (got {width!r}x{height!r})")
    return int(width), int(height)


def parse_resolution(text: str) -> tuple[int, int]:
    """``"WxH"`` (e.g. ``"1200x680"``) as ``(width, height)``; ValueError with a one-line reason
    for anything else or sizes out of bounds."""
    match = _RESOLUTION.fullmatch(text)
    if match is not None and MIN_IMAGE_SIDE <= int(match[1]) <= MAX_IMAGE_SIDE and MIN_IMAGE_SIDE <= int(match[2]) <= MAX_IMAGE_SIDE:
        return int(match[1]), int(match[2])
    raise ValueError(f"expected WxH, width and height in pixels from {MIN_IMAGE_SIDE} to {MAX_IMAGE_SIDE}, "
                     f"e.g. 1200x680 (got {text!r})")


def preset_config(preset: str, overrides: dict | None = None, *, resolution: tuple[int, int] | None = None) -> SynthConfig:
    """The named preset with ``overrides`` (nested, e.g. ``{"camera": {"frames": 30}}``) applied.

    ``resolution`` ``(width, height)`` sets the image size, nothing else: the world and the walk
    do not depend on it, and the intrinsics follow from it with the preset's horizontal field
    of view (see :func:`shared.synth.pipeline.intrinsics`). ``overrides`` may name
    ``camera.width``/``camera.height`` too only with the same values.

    Raises :class:`ConfigError` naming the preset and every bad key (or the bad resolution).
    """
    if preset not in PRESETS:
        raise ConfigError(f"unknown synth preset {preset!r}; choose one of {', '.join(sorted(PRESETS))}")
    data = deep_merge(PRESETS[preset], overrides or {})
    source = f"synth preset {preset!r}" + (" with overrides" if overrides else "")
    if resolution is not None:
        try:
            width, height = check_resolution(*resolution)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: resolution: {exc}") from None
        camera = (overrides or {}).get("camera")
        for key, value in (("width", width), ("height", height)):
            if isinstance(camera, dict) and key in camera and camera[key] != value:
                raise ConfigError(f"{source}: camera.{key} {camera[key]!r} disagrees with resolution {width}x{height}")
        data = deep_merge(data, {"camera": {"width": width, "height": height}})
        source += f" at {width}x{height}"
    return validate(SynthConfig, data, source)
