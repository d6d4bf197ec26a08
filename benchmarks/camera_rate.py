"""Benchmark: does the robot side keep up with a camera? Fusion, tracker, ``trackgraph map`` and
the live ROS 2 chain at Replica resolution (issue 35's measuring stick).

Run from the repository root::

    python benchmarks/camera_rate.py --quick           # 60 frames, one live rate (15 Hz)
    python benchmarks/camera_rate.py                   # 240 frames, live at 10, 15 and 30 Hz
    python benchmarks/camera_rate.py --parts fusion,tracker --frames 120 -v

Frames: the ``demo`` preset's walk (seed 0) rendered at ``--resolution`` (default 1200x680,
Replica's size) in ``--walk-frames`` frames (default the preset's own 900, so consecutive
frames are as far apart as in the preset), once, into ``OUT/camera_rate/sequences``; every part
takes its first ``--frames``. Config: ``deploy/configs/classical.yaml`` (no learned weights:
the robot path) with ``fusion.tsdf.voxel_size`` = ``--voxel`` (default 3 cm). Parts
(``--parts``, default all), each a key of the JSON:

* ``fusion``: :class:`services.fusion.session.FusionSession` alone on an ``InProcessBus``, with
  a ``MapStore`` (the write-ahead journal on, snapshots as configured) and ``vl/embed`` served
  for its room labels. Its input is prepared beforehand and untimed: the config's tracker
  session (classical features, keyframe masks answered at once) turns the frames into the
  TrackedFrame and TrackFeatures messages it sends, in its order, so fusion sees what it sees
  on the robot (a keyframe every ``tracker.keyframe_interval`` frames, propagated frames with
  their confidence; the ground-truth tracker's frames are all keyframes, and a keyframe costs
  fusion more). They are then handed in as fast as fusion takes them, with ``tick`` every
  0.2 s as its node does. Graph updates run on the map path a live robot uses
  (``--map-path``, default ``async``: ``fusion.map_path``).
  ``fusion_hz``: frames after the first / seconds from the first frame's ack to the last's.
  ``fusion_frame_ms``: a frame handed to the bus to its ack put (the ack's envelope stamp).
  ``update_lag_s``: per frame, from its ack (the frame is in the map) to the first graph delta
  whose ``frame_index`` covers it, by the deltas' envelope stamps, 0 for a frame whose own
  delta went out before its ack; frames no delta covered before the end are counted in
  ``frames_without_update``; ``updates``: the deltas published while frames were handed in.
  ``final_write_s``: the last frame's ack to the map written by the session's end handling (the
  tracker's ``tracks/end`` in: final delta, snapshot, export, ``run.json``).
* ``tracker``: :class:`services.tracker.session.TrackerSession` alone with the config's
  classical features; keyframe requests (every ``tracker.keyframe_interval`` frames) answered
  at once from masks and CLIP features computed beforehand with the config's keyframe_vl core
  (a request for another frame is computed on the spot and its time left out).
  ``tracker_frame_ms``: a frame handed to the bus until everything it sets off is done (its
  keyframe correction included).
* ``map``: ``trackgraph map SEQ --config classical --max-frames N --json`` in its own process;
  ``map_hz`` is its own figure (frames / seconds of the pipeline, setup left out).
* ``live``: the live chain as processes on loopback Zenoh (``trackgraph launch``'s supervisor:
  router, keyframe_vl, tracker, fusion and ``trackgraph source --ros2``); a ROS 2 bag of the
  frames with 30 Hz stamps is played by ``trackgraph ros2 play --rate HZ/30`` in rmw_zenoh's
  convention, at each rate of ``--rates`` (default 10, 15, 30; ``--quick`` 15). Once the
  player is done the source is stopped (SIGINT: its end of sequence goes out) and fusion
  writes its map. ``live_mapped_share``: frames in fusion's map / colour frames played.

In the fusion and tracker parts the first frame is left out of the rates and percentiles
(warm-up: compiled kernels loaded, first allocations) and reported as ``first_frame_ms``.

Writes ``OUT/camera_rate.json`` (``--out``, default benchmarks/out) and prints a table with
issue 35's targets. A part that fails records ``{"error": ...}`` and the script exits 1 with
one line naming it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from shared.logs import setup_logging  # noqa: E402

log = logging.getLogger("bench.camera_rate")

DEFAULT_OUT = ROOT / "benchmarks" / "out"
RESULT = "camera_rate.json"
CONFIG = ROOT / "deploy" / "configs" / "classical.yaml"
PRESET, SEED = "demo", 0
PARTS = ("fusion", "tracker", "map", "live")
DEFAULT_RESOLUTION = (1200, 680)
DEFAULT_FRAMES, QUICK_FRAMES = 240, 60
LIVE_RATES, QUICK_RATES = (10.0, 15.0, 30.0), (15.0,)
BAG_HZ = 30.0
"""Stamp rate of the bag the live part plays; ``ros2 play --rate`` scales it to each rate."""
TICK_S = 0.2
"""How often the fusion part ticks its session (as services/fusion/node.py does)."""
STARTUP_S = 300.0
"""Longest wait for the live chain's processes to be up (models, imports on a busy machine)."""
FINISH_S = 300.0
"""Longest wait, once the player is done, for fusion to write its map and the launch to end."""

TARGETS: dict[str, tuple[str, float]] = {
    "fusion_hz": (">=", 30.0),
    "fusion_frame_ms_p99": ("<=", 33.0),
    "update_lag_s_p99": ("<=", 2.0),
    "final_write_s": ("<=", 5.0),
    "tracker_hz": (">=", 30.0),
    "map_hz": (">=", 15.0),
    "live_mapped_share@15": (">=", 0.95),
}
"""Issue 35's acceptance (on an idle 2-core machine, 1200x680, 3 cm; the final write is judged
after the 900-frame demo)."""


# ---------------------------------------------------------------------------------------------
# pure helpers


def percentile(values: Sequence[float], q: float) -> float | None:
    """The ``q``-th percentile (0-100) by linear interpolation between ranks (numpy's default);
    None for no values."""
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile q must be within 0..100, got {q}")
    xs = sorted(float(v) for v in values)
    if not xs:
        return None
    pos = (len(xs) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def update_lags(fused_at: dict[int, float], deltas: Sequence[tuple[float, int]]) -> tuple[list[float], int]:
    """Per frame (``fused_at``: frame index -> when it was in the map), the seconds until the
    first delta (``deltas``: (publish time, its ``frame_index``)) that covers it, never below 0;
    and how many frames no delta covers."""
    lags, uncovered = [], 0
    for k in sorted(fused_at):
        stamps = [t for t, last in deltas if last >= k]
        if not stamps:
            uncovered += 1
            continue
        lags.append(max(min(stamps) - fused_at[k], 0.0))
    return lags, uncovered


def parse_resolution(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` (e.g. 1200x680) as (width, height), by ``trackgraph synth
    --resolution``'s rule; argparse's type for --resolution."""
    from shared.synth.config import parse_resolution as synth_resolution

    try:
        return synth_resolution(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parse_parts(text: str) -> tuple[str, ...]:
    """A comma-separated list of :data:`PARTS`, in their order; argparse's type for --parts."""
    asked = [p.strip() for p in text.split(",") if p.strip()]
    bad = [p for p in asked if p not in PARTS]
    if bad or not asked:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a comma-separated list of {', '.join(PARTS)}")
    return tuple(p for p in PARTS if p in asked)


def parse_rates(text: str) -> tuple[float, ...]:
    """A comma-separated list of camera rates in Hz (each > 0); argparse's type for --rates."""
    try:
        rates = tuple(float(r) for r in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected rates in Hz separated by commas, e.g. 10,15,30") from None
    if not rates or not all(math.isfinite(r) and r > 0 for r in rates):
        raise argparse.ArgumentTypeError(f"{text!r}: every rate must be a positive number of Hz")
    return rates


def _check(value: Any, key: str) -> str:
    """``pass``/``FAIL`` against ``TARGETS[key]``, or "" without a target or a value."""
    if key not in TARGETS or not isinstance(value, (int, float)):
        return ""
    op, bound = TARGETS[key]
    ok = value >= bound if op == ">=" else value <= bound
    return f"{op} {bound:g}: {'pass' if ok else 'FAIL'}"


def _num(value: Any, fmt: str) -> str:
    return "-" if not isinstance(value, (int, float)) else format(value, fmt)


def table(res: dict[str, Any]) -> str:
    """The printed summary: one row per figure, with issue 35's target where it has one."""
    w, h = res["resolution"]
    m = res.get("machine") or {}
    lines = [
        f"camera_rate: {res['preset']} walk at {w}x{h}, voxel {res['voxel_size'] * 100:g} cm, {res['frames']} frames, "
        f"classical config{' (quick)' if res.get('quick') else ''}; commit {res.get('commit')}; "
        f"{m.get('cpus')} CPUs ({m.get('cpu')}), load {m.get('loadavg')}",
        "",
        "| part | figure | value | target |",
        "|---|---|---|---|",
    ]

    def row(part: str, figure: str, value: str, target: str = "") -> None:
        lines.append(f"| {part} | {figure} | {value} | {target} |")

    for part in res.get("parts", ()):
        r = res.get(part) or {}
        if "error" in r and part != "live":
            row(part, "error", str(r["error"]))
            continue
        if part == "fusion":
            row("fusion", "fusion_hz (journal on)", f"{_num(r.get('fusion_hz'), '.2f')} Hz", _check(r.get("fusion_hz"), "fusion_hz"))
            row("fusion", "frame ms p50 / p99", f"{_num(r.get('fusion_frame_ms_p50'), '.1f')} / {_num(r.get('fusion_frame_ms_p99'), '.1f')}",
                _check(r.get("fusion_frame_ms_p99"), "fusion_frame_ms_p99"))  # fmt: skip
            row("fusion", "update lag s p50 / p99", f"{_num(r.get('update_lag_s_p50'), '.2f')} / {_num(r.get('update_lag_s_p99'), '.2f')}",
                _check(r.get("update_lag_s_p99"), "update_lag_s_p99"))  # fmt: skip
            row("fusion", "updates", f"{r.get('updates')} ({r.get('frames_without_update')} frames after the last)")
            row("fusion", "final map write", f"{_num(r.get('final_write_s'), '.2f')} s", _check(r.get("final_write_s"), "final_write_s") + " (900 frames)")
        elif part == "tracker":
            row("tracker", "tracker_hz (classical)", f"{_num(r.get('tracker_hz'), '.2f')} Hz", _check(r.get("tracker_hz"), "tracker_hz"))
            row("tracker", "frame ms p50 / p99", f"{_num(r.get('tracker_frame_ms_p50'), '.1f')} / {_num(r.get('tracker_frame_ms_p99'), '.1f')}")
            row("tracker", "keyframe ms p50", f"{_num(r.get('keyframe_ms_p50'), '.1f')} ({r.get('keyframes')} keyframes)")
        elif part == "map":
            row("map", "map_hz (trackgraph map, classical)", f"{_num(r.get('map_hz'), '.2f')} Hz", _check(r.get("map_hz"), "map_hz"))
        elif part == "live":
            if not r.get("rates"):
                row("live", "error", str(r.get("error")))
            for key, lr in (r.get("rates") or {}).items():
                label = f"live {key} Hz"
                if "error" in lr:
                    row(label, "error", str(lr["error"]))
                    continue
                share = lr.get("live_mapped_share")
                value = f"{_num(share * 100 if share is not None else None, '.0f')}% ({lr.get('frames_in_map')} of {lr.get('frames_played')})"
                target = _check(share, "live_mapped_share@15") if float(key) == 15.0 else ""
                row(label, "mapped share", value, target)
                row(label, "source published / dropped", f"{lr.get('published')} / {lr.get('dropped')}")
    return "\n".join(lines)


def machine() -> dict[str, Any]:
    """The bench's machine record (OS, CPU model and count, Python, GPUs) and the load when
    the run started: rates on a shared machine are read against it."""
    from services.bench.runs import machine as bench_machine

    return {**bench_machine(), "loadavg": [round(x, 2) for x in os.getloadavg()]}


# ---------------------------------------------------------------------------------------------
# frames and config


def make_sequence(work: Path, size: tuple[int, int], walk_frames: int) -> Path:
    """The demo walk at ``size`` in ``walk_frames`` frames, rendered once into ``work/sequences``."""
    from shared.synth import run_synth

    w, h = size
    seq = work / "sequences" / f"{PRESET}-seed{SEED}-{w}x{h}-{walk_frames}"
    if not (seq / "traj.txt").is_file():
        log.info("rendering the %s walk at %dx%d in %d frames into %s (once)", PRESET, w, h, walk_frames, seq)
        run_synth(PRESET, SEED, seq, {"camera": {"frames": walk_frames}}, resolution=(w, h), overwrite=True, progress=sys.stderr.isatty())
    return seq


def load_frames(seq: Path, n: int) -> list:
    """The first ``n`` frames of ``seq`` as ``Frame`` messages, decoded beforehand."""
    from tqdm import tqdm

    from shared.datasets import open_sequence

    reader = open_sequence(seq, "replica")
    return [reader.frame(i) for i in tqdm(range(n), desc="load frames", unit="frame", disable=None)]


SETS: list[str] = []
"""``--set`` overrides, for every part (the config is ``CONFIG`` with these)."""


def system_config(seq: Path, voxel: float, sets: Sequence[str] = ()):
    """The classical config at ``voxel``, with its simulated backends' ground truth at ``seq``."""
    from shared.config import load_config

    return load_config(CONFIG, [f"fusion.tsdf.voxel_size={voxel}", *SETS, *sets]).with_ground_truth(seq)


def _summary_ms(seconds: Sequence[float], prefix: str) -> dict[str, float | None]:
    ms = [1e3 * s for s in seconds]
    return {f"{prefix}_p50": percentile(ms, 50), f"{prefix}_p99": percentile(ms, 99), f"{prefix}_max": max(ms) if ms else None}


# ---------------------------------------------------------------------------------------------
# part 1: fusion's session


def tracked_messages(cfg, frames: list, keyframe_vl) -> tuple[list, Any]:
    """What the config's tracker session (classical features) sends fusion for ``frames``:
    the TrackedFrame and TrackFeatures messages in its order, and its ``tracks/end``. Keyframe
    requests are answered at once by ``keyframe_vl``'s core (``wait_for_masks``), so the
    messages are those of a tracker whose masks come on time: a keyframe every
    ``tracker.keyframe_interval`` frames, propagated frames with their confidence between."""
    from tqdm import tqdm

    from services.tracker.build import build_tracker
    from services.tracker.session import TrackerSession
    from shared.messages.frames import EndOfSequence, Frame, TrackedFrame
    from shared.messages.keyframes import (
        KeyframeMasks,
        KeyframeRequest,
        MaskFeatures,
        TrackFeatures,
    )
    from shared.runtime.bus import InProcessBus

    bus = InProcessBus(cfg.robot_id)
    tracker = TrackerSession(bus, cfg, build_tracker(cfg), wait_for_masks=True)
    t = tracker.topics
    out: list = []
    ends: list = []
    masks_out, features_out = bus.publisher(t.keyframe_masks, KeyframeMasks), bus.publisher(t.keyframe_features, MaskFeatures)

    def on_request(env) -> None:
        msg, feats = answer(keyframe_vl, env.body)
        masks_out.put(msg)
        features_out.put(feats)

    bus.subscribe(t.keyframe_request, KeyframeRequest, on_request, capacity=4)
    bus.subscribe(t.tracks_frame, TrackedFrame, lambda env: out.append(env.body), capacity=1)
    bus.subscribe(t.tracks_features, TrackFeatures, lambda env: out.append(env.body), capacity=1)
    bus.subscribe(t.tracks_end, EndOfSequence, lambda env: ends.append(env.body), capacity=1)
    frames_out = bus.publisher(t.frames, Frame)
    try:
        for fr in tqdm(frames, desc="tracked frames (classical)", unit="frame", disable=None):
            frames_out.put(fr)
            bus.drain()
        bus.publisher(t.end_of_sequence, EndOfSequence).put(
            EndOfSequence(frames_published=len(frames), frames_dropped=0, last_frame_index=frames[-1].frame_index))
        bus.drain()
    finally:
        tracker.close()
        bus.close()
    if not ends:
        raise RuntimeError("the tracker passed no tracks/end on")
    return out, ends[-1]


def run_fusion(seq: Path, voxel: float, n: int, work: Path, map_path: str = "async") -> dict[str, Any]:
    from tqdm import tqdm

    from services.fusion.core import FusionCore
    from services.fusion.session import FusionSession
    from services.keyframe_vl.build import build_keyframe_vl
    from shared.graph.store import MapStore
    from shared.messages.frames import EndOfSequence, FrameAck, TrackedFrame
    from shared.messages.graph import GraphDelta
    from shared.messages.keyframes import TrackFeatures
    from shared.messages.rpc import EmbedReply, EmbedRequest
    from shared.runtime.bus import InProcessBus

    cfg = system_config(seq, voxel, [f"fusion.map_path={map_path}"])
    keyframe_vl = build_keyframe_vl(cfg)  # the tracker's keyframe masks; vl/embed for the room labels
    t_prep = time.monotonic()
    messages, end = tracked_messages(cfg, load_frames(seq, n), keyframe_vl)
    prepare_s = time.monotonic() - t_prep

    out = work / "fusion_map"
    shutil.rmtree(out, ignore_errors=True)
    # Envelope stamps on the monotonic clock: an ack's and a delta's stamp are when they were put.
    bus = InProcessBus(cfg.robot_id, clock=time.monotonic)
    session = FusionSession(bus, cfg, FusionCore(cfg.fusion, device=cfg.tracker.device), store=MapStore(out / "graph", robot_id=cfg.robot_id), out=out)
    t = session.topics
    bus.serve(t.vl_embed, EmbedRequest, EmbedReply, lambda env: keyframe_vl.embed(env.body))
    acked: dict[int, float] = {}
    deltas: list[tuple[float, int]] = []

    def on_ack(env) -> None:
        if env.body.service == "fusion":  # the first ack of a frame: a watermark repeats the newest
            acked.setdefault(env.body.frame_index, env.stamp)

    bus.subscribe(t.frame_ack, FrameAck, on_ack, capacity=1)
    bus.subscribe(t.graph_delta, GraphDelta, lambda env: deltas.append((env.stamp, env.body.frame_index)), capacity=1)
    frames_in, features_in = bus.publisher(t.tracks_frame, TrackedFrame), bus.publisher(t.tracks_features, TrackFeatures)
    handed: dict[int, float] = {}
    try:
        session.fetch_room_labels()
        last_tick = time.monotonic()
        for msg in tqdm(messages, desc="fusion", unit="msg", disable=None):
            if isinstance(msg, TrackedFrame):
                handed[msg.frame.frame_index] = time.monotonic()
                frames_in.put(msg)
            else:
                features_in.put(msg)
            bus.drain()
            now = time.monotonic()
            if now - last_tick >= TICK_S and msg is not messages[-1]:
                session.tick(now)
                bus.drain()
                last_tick = now
        # an update still being built on the map thread goes out at the next tick, as live
        session.map_path.join()
        session.tick(time.monotonic())
        bus.drain()
        updates = len(deltas)
        fed = dict(acked)
        t_end = time.monotonic()
        bus.publisher(t.tracks_end, EndOfSequence).put(end)
        bus.drain()
        while not session.finished.is_set():
            if time.monotonic() - t_end > FINISH_S:
                raise RuntimeError(f"fusion did not finish its map within {FINISH_S:.0f} s of the end of the sequence")
            session.tick(time.monotonic())
            bus.drain()
            time.sleep(0.01)
        written = time.monotonic()
        delivery = session.delivery()
    finally:
        session.close(save=False)
        bus.close()
    missing = sorted(set(handed) - set(fed))
    if missing:
        raise RuntimeError(f"fusion acknowledged {len(fed)} of {len(handed)} frames (first missing: {missing[0]})")
    if not (out / "run.json").is_file():
        raise RuntimeError(f"fusion finished without writing {out / 'run.json'}")
    if delivery.get("journal") is None:
        raise RuntimeError("fusion kept no write-ahead journal (fusion.journal.enabled is off in the config)")
    order = sorted(fed)
    per_frame = [fed[k] - handed[k] for k in order]
    lags, uncovered = update_lags(fed, deltas[:updates])
    span = fed[order[-1]] - fed[order[0]]
    run = json.loads((out / "run.json").read_text())
    return {
        "input": "the classical tracker session, masks on time, prepared beforehand",
        "map_path": map_path,
        "frames": len(order),
        "fusion_hz": (len(order) - 1) / span if span > 0 else None,
        **_summary_ms(per_frame[1:], "fusion_frame_ms"),
        "first_frame_ms": 1e3 * per_frame[0],
        "update_lag_s_p50": percentile(lags, 50),
        "update_lag_s_p99": percentile(lags, 99),
        "updates": updates,
        "frames_without_update": uncovered,
        "final_write_s": written - fed[order[-1]],
        "segments": run.get("segments"),
        "frames_in_map": delivery.get("frames_in_map"),
        "journal": delivery.get("journal"),
        "prepare_s": round(prepare_s, 1),
        "map": str(out),
    }


# ---------------------------------------------------------------------------------------------
# part 2: the tracker's session


def keyframe_answers(core, frames: list, every: int) -> dict[int, tuple[Any, Any]]:
    """keyframe_vl's masks and CLIP features for every ``every``-th frame, as the tracker
    would ask for them."""
    from tqdm import tqdm

    from shared.messages.keyframes import KeyframeRequest

    answers = {}
    for fr in tqdm([f for f in frames if f.frame_index % every == 0], desc="keyframe masks", unit="keyframe", disable=None):
        answers[fr.frame_index] = answer(core, KeyframeRequest(frame_index=fr.frame_index, rgb=fr.rgb, depth=fr.depth,
                                                               depth_scale=fr.depth_scale, intrinsics=fr.intrinsics))  # fmt: skip
    return answers


def answer(core, req) -> tuple[Any, Any]:
    """(KeyframeMasks, MaskFeatures) of one request, as keyframe_vl computes them."""
    image, masks, msg = core.segment(req)
    return msg, core.features(image, masks)


def run_tracker(seq: Path, voxel: float, n: int) -> dict[str, Any]:
    from tqdm import tqdm

    from services.keyframe_vl.build import build_keyframe_vl
    from services.tracker.build import build_tracker
    from services.tracker.session import TrackerSession
    from shared.messages.frames import Frame
    from shared.messages.keyframes import KeyframeMasks, KeyframeRequest, MaskFeatures
    from shared.runtime.bus import InProcessBus

    cfg = system_config(seq, voxel)
    frames = load_frames(seq, n)
    keyframe_vl = build_keyframe_vl(cfg)
    every = cfg.tracker.keyframe_interval
    t_prep = time.monotonic()
    answers = keyframe_answers(keyframe_vl, frames, every)
    prepare_s = time.monotonic() - t_prep

    bus = InProcessBus(cfg.robot_id)
    session = TrackerSession(bus, cfg, build_tracker(cfg))
    t = session.topics
    masks_out, features_out = bus.publisher(t.keyframe_masks, KeyframeMasks), bus.publisher(t.keyframe_features, MaskFeatures)
    off = {"s": 0.0, "unplanned": 0, "requests": set()}

    def on_request(env) -> None:
        req = env.body
        off["requests"].add(req.frame_index)
        if req.frame_index not in answers:  # not a planned keyframe: computed now, its time left out
            t0 = time.perf_counter()
            answers[req.frame_index] = answer(keyframe_vl, req)
            off["s"] += time.perf_counter() - t0
            off["unplanned"] += 1
        msg, feats = answers.pop(req.frame_index)
        masks_out.put(msg)
        features_out.put(feats)

    bus.subscribe(t.keyframe_request, KeyframeRequest, on_request, capacity=4)
    frames_in = bus.publisher(t.frames, Frame)
    per_frame, ends = [], []
    try:
        for fr in tqdm(frames, desc="tracker", unit="frame", disable=None):
            t0, off0 = time.perf_counter(), off["s"]
            frames_in.put(fr)
            bus.drain()
            end = time.perf_counter()
            per_frame.append(end - t0 - (off["s"] - off0))
            ends.append(end - off["s"])  # the work timeline, computed keyframes left out
        tracked = session.frames
    finally:
        session.close()
        bus.close()
    if tracked != len(frames):
        raise RuntimeError(f"the tracker tracked {tracked} of {len(frames)} frames")
    key = [s for fr, s in zip(frames, per_frame, strict=True) if fr.frame_index in off["requests"]][1:]
    span = ends[-1] - ends[0]
    return {
        "frames": len(frames),
        "tracker_hz": (len(frames) - 1) / span if span > 0 else None,
        **_summary_ms(per_frame[1:], "tracker_frame_ms"),
        "first_frame_ms": 1e3 * per_frame[0],
        "keyframe_interval": every,
        "keyframes": len(off["requests"]),
        "keyframe_ms_p50": percentile([1e3 * s for s in key], 50),
        "keyframes_unplanned": off["unplanned"],
        "features": cfg.tracker.features.backend,
        "wait_for_masks": cfg.tracker.wait_for_masks,
        "prepare_s": round(prepare_s, 1),
    }


# ---------------------------------------------------------------------------------------------
# part 3: trackgraph map


def run_map(seq: Path, voxel: float, n: int, work: Path) -> dict[str, Any]:
    out = work / "map"
    cmd = [sys.executable, "-m", "services.cli", "map", str(seq), "--config", "classical", "--set", f"fusion.tsdf.voxel_size={voxel}",
           "--max-frames", str(n), "--out", str(out), "--json", *(a for item in SETS for a in ("--set", item))]  # fmt: skip
    log.info("trackgraph map of %d frames", n)
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"}, check=False)
    if proc.returncode != 0:
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        raise RuntimeError(f"trackgraph map failed: {lines[-1] if lines else f'exit {proc.returncode}'}")
    rows = [ln for ln in proc.stdout.splitlines() if ln.strip().startswith("{")]
    if not rows:
        raise RuntimeError("trackgraph map printed no --json summary")
    run = json.loads(rows[-1])
    return {"map_hz": run.get("hz"), **{k: run.get(k) for k in ("frames", "seconds", "setup_seconds", "peak_rss_mb", "segments")}, "out": str(out)}


# ---------------------------------------------------------------------------------------------
# part 4: the live chain


def _wait_for(done: Callable[[], bool], timeout: float, what: str, sup) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        if sup.error is not None:
            raise RuntimeError(sup.error)
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} after {timeout:.0f} s")
        time.sleep(0.2)


def _nested_sets(tree: dict[str, Any]) -> dict[str, Any]:
    """``tree`` with the ``--set`` overrides merged in (dotted keys to nested dicts)."""
    from shared.config.overrides import parse_set, read_value

    for item in SETS:
        path, text = parse_set(item)
        node = tree
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = read_value(".".join(path), text)
    return tree


def live_rate(seq: Path, voxel: float, bag: Path, frames: int, hz: float, work: Path) -> dict[str, Any]:
    """One live run: the chain as processes, the bag played at ``hz``, counts from the
    services' status files and fusion's ``run.json``."""
    from services.bench.rate import figure, stage_drops, stage_reports, start_live_system

    shutil.rmtree(work, ignore_errors=True)
    overrides = _nested_sets({"fusion": {"tsdf": {"voxel_size": voxel}, "map_path": "async"}, "ros2": {"link": {"convention": "rmw_zenoh", "domain_id": 0}}})
    services = [
        {"name": "router"},
        {"name": "keyframe_vl"},
        {"name": "fusion", "args": ["--exit-at-end"]},
        {"name": "tracker", "after": ["keyframe_vl"]},
        {"name": "source", "args": ["--ros2"], "finite": True, "after": ["tracker", "fusion"]},
    ]
    t0 = time.monotonic()
    plan, sup, runner = start_live_system(CONFIG, seq, work, overrides, services, restart={"max_restarts": 0})
    player = None
    try:
        _wait_for(lambda: sup.procs["source"].state == "alive", STARTUP_S, "the live chain was not up", sup)
        # The simulated VL encoder finds each keyframe's ground truth through an index of the
        # sequence's images, built on a thread from its start (10 s of a core at 1200x680):
        # harness setup a robot's real models do not have, so the camera starts after it.
        vl_log = plan.log_dir / "keyframe_vl.log"
        _wait_for(lambda: vl_log.is_file() and "ground-truth image index of" in vl_log.read_text(errors="replace"),
                  STARTUP_S, "keyframe_vl's ground-truth index was not built", sup)  # fmt: skip
        startup_s = time.monotonic() - t0
        log.info("live %g Hz: chain up in %.0f s; playing %d frames", hz, startup_s, frames)
        cmd = [sys.executable, "-m", "services.cli", "ros2", "play", str(bag), "--config", str(plan.config_path),
               "--rate", f"{hz / BAG_HZ:.6g}", "--wait", "30", "--json"]  # fmt: skip
        player = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
        stdout, stderr = player.communicate(timeout=3 * frames / hz + 120)
        if player.returncode != 0:
            lines = [ln for ln in stderr.splitlines() if ln.strip()]
            raise RuntimeError(f"ros2 play failed: {lines[-1] if lines else f'exit {player.returncode}'}")
        rows = [ln for ln in stdout.splitlines() if ln.strip().startswith("{")]
        if not rows:
            raise RuntimeError("ros2 play printed no --json summary")
        played = json.loads(rows[-1])
        # The last colour/depth pair is final after the source's wait for its pose; then its
        # end of sequence goes out and fusion writes the map.
        time.sleep(2 * plan.system.ros2.input.max_wait_s + 1.0)
        pid = sup.procs["source"].pid
        if pid is not None:
            os.kill(pid, signal.SIGINT)
        runner.join(timeout=FINISH_S)
        if runner.is_alive():
            raise RuntimeError(f"fusion did not finish its map within {FINISH_S:.0f} s of the source's end")
        if sup.error is not None:
            raise RuntimeError(sup.error)
    finally:
        if player is not None and player.poll() is None:
            player.kill()
            player.wait()
        if runner.is_alive():
            sup.stop_event.set()
            runner.join()
    reports = stage_reports(plan.log_dir)
    run_json = plan.out / "run.json"
    run = json.loads(run_json.read_text()) if run_json.is_file() else {}
    in_map = run.get("frames_in_map", figure(reports["fusion"], "frames_in_map"))
    sent = (played.get("topics") or {}).get(plan.system.ros2.input.rgb_topic)
    ros2 = figure(reports["source"], "ros2") or {}
    drops = stage_drops(reports)
    return {
        "rate_hz": hz,
        "frames_played": sent,
        "published": figure(reports["source"], "published"),
        "dropped": figure(reports["source"], "dropped"),
        "rejected": {k: v for k, v in (ros2.get("rejected") or {}).items() if v},
        "tracker_dropped": drops.get("tracker"),
        "fusion_dropped": drops.get("fusion"),
        "frames_in_map": in_map,
        "live_mapped_share": in_map / sent if sent and in_map is not None else None,
        "player_late_s": played.get("late_s"),
        "startup_s": round(startup_s, 1),
        "seconds": round(time.monotonic() - t0, 1),
        "logs": str(plan.log_dir),
    }


def run_live(seq: Path, voxel: float, frames: int, rates: Sequence[float], work: Path) -> dict[str, Any]:
    from shared.ros2.bagio import write_sequence_bag

    bag = work / "bags" / f"{seq.name}-{frames}f-{BAG_HZ:g}hz"
    if not (bag / "metadata.yaml").is_file():
        log.info("writing the first %d frames as a ROS 2 bag at %g Hz into %s (once)", frames, BAG_HZ, bag)
        write_sequence_bag(seq, bag, rate_hz=BAG_HZ, max_frames=frames, overwrite=True)
    out: dict[str, Any] = {"frames": frames, "bag": str(bag), "bag_hz": BAG_HZ, "rates": {}}
    errors = []
    for hz in rates:
        key = f"{hz:g}"
        folder = work / "live" / f"{key}hz"
        try:
            out["rates"][key] = live_rate(seq, voxel, bag, frames, hz, folder)
        except Exception as exc:  # noqa: BLE001 - the other rates still run; the part reports the failure
            log.exception("live at %s Hz failed", key)
            out["rates"][key] = {"rate_hz": hz, "error": f"{type(exc).__name__}: {exc}", "logs": str(folder / "map" / "logs")}
            errors.append(f"{key} Hz: {exc}")
    if errors:
        out["error"] = "; ".join(errors)
    return out


# ---------------------------------------------------------------------------------------------


def run(args: argparse.Namespace) -> dict[str, Any]:
    from services.bench.runs import git_commit

    work = args.out / "camera_rate"
    res: dict[str, Any] = {
        "benchmark": "camera_rate",
        "resolution": list(args.resolution),
        "voxel_size": args.voxel,
        "frames": args.frames,
        "walk_frames": args.walk_frames,
        "preset": PRESET,
        "seed": SEED,
        "config": str(CONFIG.relative_to(ROOT)),
        "quick": args.quick,
        "parts": list(args.parts),
        "sets": list(args.set),
        "commit": git_commit(),  # the bench's: "-dirty" with uncommitted changes
        "machine": machine(),
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
    }
    t0 = time.monotonic()
    seq = make_sequence(work, args.resolution, args.walk_frames)
    res["sequence"] = str(seq)
    runners: dict[str, Callable[[], dict[str, Any]]] = {
        "fusion": lambda: run_fusion(seq, args.voxel, args.frames, work, args.map_path),
        "tracker": lambda: run_tracker(seq, args.voxel, args.frames),
        "map": lambda: run_map(seq, args.voxel, args.frames, work),
        "live": lambda: run_live(seq, args.voxel, args.frames, args.rates, work),
    }
    for part in args.parts:
        log.info("part %s", part)
        t_part = time.monotonic()
        try:
            res[part] = runners[part]()
        except Exception as exc:  # noqa: BLE001 - recorded; the other parts still run
            log.exception("part %s failed", part)
            res[part] = {"error": f"{type(exc).__name__}: {exc}"}
        res[part]["wall_s"] = round(time.monotonic() - t_part, 1)
    res["wall_s"] = round(time.monotonic() - t0, 1)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", type=parse_resolution, default=DEFAULT_RESOLUTION, metavar="WxH", help="frame size (default 1200x680)")
    ap.add_argument("--voxel", type=float, default=0.03, metavar="M", help="fusion.tsdf.voxel_size in metres (default 0.03)")
    ap.add_argument("--frames", type=int, metavar="N", help=f"frames per part (default {DEFAULT_FRAMES}; --quick {QUICK_FRAMES})")
    ap.add_argument("--walk-frames", type=int, metavar="N", help="frames the demo walk is rendered in (default the preset's own, 900)")
    ap.add_argument("--parts", type=parse_parts, default=PARTS, metavar="LIST", help=f"comma-separated parts to run (default {','.join(PARTS)})")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override for every part (repeatable)")
    ap.add_argument("--map-path", choices=["sync", "async"], default="async", help="fusion part: fusion.map_path (default async, a live robot's)")
    ap.add_argument("--rates", type=parse_rates, metavar="HZ,...", help="live camera rates (default 10,15,30; --quick 15)")
    ap.add_argument("--quick", action="store_true", help=f"{QUICK_FRAMES} frames and one live rate")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, metavar="DIR", help=f"{RESULT} and the work folder camera_rate/ (default benchmarks/out)")
    ap.add_argument("-v", "--verbose", action="count", default=0)
    args = ap.parse_args(argv)
    SETS[:] = args.set
    if args.walk_frames is None:
        from shared.synth.config import preset_config

        args.walk_frames = preset_config(PRESET).camera.frames
    args.frames = args.frames or (QUICK_FRAMES if args.quick else DEFAULT_FRAMES)
    args.rates = args.rates or (QUICK_RATES if args.quick else LIVE_RATES)
    if args.frames < 3:
        ap.error(f"--frames: at least 3, got {args.frames}")
    if args.walk_frames < args.frames:
        ap.error(f"--frames {args.frames} is more than the walk's --walk-frames {args.walk_frames}")
    if not (math.isfinite(args.voxel) and 0.005 <= args.voxel <= 1.0):
        ap.error(f"--voxel: expected metres within 0.005..1, got {args.voxel}")
    setup_logging(args.verbose, service="bench")
    args.out = args.out.resolve()
    res = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / RESULT
    path.write_text(json.dumps(res, indent=2))
    print(table(res))
    print(f"wrote {path} ({res['wall_s']:.0f} s)")
    failed = [p for p in args.parts if "error" in res[p]]
    if failed:
        print("camera_rate: failed: " + "; ".join(f"{p}: {res[p]['error']}" for p in failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
