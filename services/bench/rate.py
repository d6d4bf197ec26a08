"""The highest input rate the distributed system sustains without dropping a frame.

A trial starts the router, keyframe_vl, tracker and fusion as separate processes on loopback
Zenoh (``trackgraph launch``'s Supervisor), then the source in ``live`` mode at the trial's
rate. A live source never waits for a slow stage, so a stage that cannot keep up drops frames,
and each drop is counted where it happens: the source (frames it was too late to send), the
tracker (frames its newest-only input replaced), keyframe_vl (keyframe requests its queue had
no room for) and fusion (tracked frames its bounded queue had no room for). A rate is
sustained when no stage dropped anything, every frame published reached the map, the map kept
pace (its frames were fused, first to last, at 90% of the source's rate or more), and so did
keyframe_vl: every keyframe got its masks and CLIP features back, first to last at 90% of the
rate the tracker asked for them (``services.tracker.pace``). Every count comes from the
``status.json`` each service writes beside its log at stop (its last ``ServiceStatus``), never
from log text. The pace conditions matter
because buffers hide a slow stage for a while: fusion queues every tracked frame rather than
lose it, and a live tracker never waits for masks, so a keyframe_vl that cannot keep up only
makes its answers later and later while the frames flow on, tracked on stale labels.

The search doubles the rate after a sustained trial and halves it after a failed one until it
has bracketed the limit, then bisects; the answer is the highest sustained rate tried.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import socket
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import yaml

from shared.messages.status import ServiceStatus
from shared.runtime.status import read_status, status_path

log = logging.getLogger(__name__)

PACE_SHARE = 0.9
"""A sustained rate: the map took in frames (first to last fused) at least this share of the
source's rate, besides dropping none."""
STARTUP_ALLOWANCE_S = 180.0
"""A trial is stopped when it runs this much longer than its frames take at its rate."""
KEYFRAME_TIMEOUT_S = 600.0
"""``tracker.keyframe_timeout_s`` in a trial (unless the config's is longer): the pace rule
judges late answers, so a tracker that gave up on slow masks must not hide them. Long
enough for the paper's models on a CPU (about a minute a keyframe on two cores)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


STAGES = ("source", "tracker", "keyframe_vl", "fusion")
DROP_INPUT = {"tracker": "frames", "keyframe_vl": "keyframe_request", "fusion": "tracks_frame"}
"""The input whose ``dropped`` counts a stage's lost work (the source counts its own, in its
``dropped`` figure)."""


def stage_reports(log_dir: Path, names: tuple[str, ...] = STAGES) -> dict[str, ServiceStatus | None]:
    """Each service's last report, from ``<log_dir>/<service>.status.json``; None for one that
    wrote none (it crashed, or never started) or whose file is not a report (logged)."""
    out: dict[str, ServiceStatus | None] = {}
    for name in names:
        path = status_path(log_dir, name)
        out[name] = None
        if path.is_file():
            try:
                out[name] = read_status(path)
            except ValueError as exc:
                log.warning("%s", exc)
    return out


def figure(st: ServiceStatus | None, name: str) -> Any:
    """A report's own figure ``name``, None without a report or the figure."""
    return None if st is None else st.figures.get(name)


def input_count(st: ServiceStatus | None, name: str, what: str = "dropped") -> int | None:
    """Counter ``what`` of input ``name`` in a report; None without a report or that input."""
    if st is None:
        return None
    for inp in st.inputs:
        if inp.name == name:
            return int(getattr(inp, what))
    return None


def stage_drops(reports: dict[str, ServiceStatus | None]) -> dict[str, int | None]:
    """Frames (or keyframe requests) each stage lost, as the trial's ``drops``."""
    drops: dict[str, int | None] = {"source": figure(reports.get("source"), "dropped")}
    for stage, inp in DROP_INPUT.items():
        drops[stage] = input_count(reports.get(stage), inp)
    return drops


def start_live_system(
    config: Path, sequence: Path, work: Path, overrides: dict, services: list[dict], **launch: Any
) -> tuple[Any, Any, threading.Thread]:
    """A launch file in ``work`` for ``services`` over ``config`` with ``overrides``, on a free
    loopback port, planned (map in ``work/map``) and supervised in a background thread:
    (plan, supervisor, thread). Extra launch-file keys go in ``launch``."""
    from services.launch import Supervisor, plan_launch
    from shared.config.base import deep_merge
    from shared.config.overrides import as_sets

    work.mkdir(parents=True, exist_ok=True)
    port = free_port()
    doc = {
        "config": str(Path(config).resolve()),  # the launch file lives in ``work``
        # Shared memory has dropped messages under load in some Zenoh versions: a drop here
        # must be the system's, not the transport's.
        "set": as_sets(deep_merge({"transport": {"shared_memory": False}}, overrides)),
        "connect": [f"tcp/127.0.0.1:{port}"],
        "listen": [f"tcp/127.0.0.1:{port}"],
        "services": services,
        "exit_when_finished": True,
        **launch,
    }
    path = work / "launch.yaml"
    path.write_text(yaml.safe_dump(doc))
    plan = plan_launch(path, sequence=sequence, out=work / "map")
    sup = Supervisor(plan, status=False)
    runner = threading.Thread(target=sup.run, daemon=True)
    runner.start()
    return plan, sup, runner


def trial_frames(rate_hz: float, seconds: float | None, frames: int | None, keyframe_interval: int) -> int | None:
    """Frames in a trial at ``rate_hz``: ``frames``; or, with ``seconds``, as many as the
    source sends in that time but never fewer than two keyframes' worth
    (``keyframe_interval + 1``), so that keyframe_vl's pace can be judged."""
    if seconds is None:
        return frames
    return max(math.ceil(seconds * rate_hz), keyframe_interval + 1)


def live_trial(
    sequence: Path, config: Path, work: Path, rate_hz: float, frames: int | None, *, extra_services: Sequence[dict] = ()
) -> dict[str, Any]:
    """One run of the live system at ``rate_hz`` over the first ``frames`` frames.
    ``extra_services``: launch-file entries of more services started with it (e.g.
    ``{"name": "query"}``); the sustained-rate rule still judges the four stages alone."""
    from shared.config.root import load_config

    source: dict[str, Any] = {"mode": "live", "rate_hz": float(rate_hz)}
    if frames:
        source["max_frames"] = int(frames)
    timeout = max(load_config(config).tracker.keyframe_timeout_s, KEYFRAME_TIMEOUT_S)
    services = [
        {"name": "router"},
        {"name": "keyframe_vl"},
        {"name": "fusion", "args": ["--exit-at-end"]},
        *(dict(s) for s in extra_services),
        {"name": "tracker", "after": ["keyframe_vl"]},
        {"name": "source", "after": ["tracker", "fusion"]},
    ]
    t0 = time.monotonic()
    overrides = {"source": source, "tracker": {"keyframe_timeout_s": timeout}}
    shutil.rmtree(work, ignore_errors=True)  # an earlier run's map and logs are not this trial's
    plan, sup, runner = start_live_system(config, sequence, work, overrides, services, restart={"max_restarts": 0})
    out = plan.out
    budget = (frames or 10_000) / rate_hz + STARTUP_ALLOWANCE_S
    runner.join(timeout=budget)
    timed_out = runner.is_alive()
    if timed_out:
        log.warning("trial at %.1f Hz still running after %.0f s; stopping it", rate_hz, budget)
        sup.stop_event.set()
        runner.join()
    res, meets_rule = trial_result(plan.log_dir, out, rate_hz)
    ok = not timed_out and sup.error is None and meets_rule
    return {
        **res,
        "sustained": bool(ok),
        "error": sup.error or ("timed out" if timed_out else None),
        "seconds": round(time.monotonic() - t0, 1),
    }


def trial_result(log_dir: Path, map_dir: Path, rate_hz: float) -> tuple[dict[str, Any], bool]:
    """What one trial's services reported (their ``status.json`` in ``log_dir``) and its map
    (``map_dir/run.json``) say: the trial's figures, and whether they meet the sustained-rate
    rule (the caller adds how the run itself ended)."""
    from services.tracker.pace import kept_up

    reports = stage_reports(log_dir)
    run = json.loads((map_dir / "run.json").read_text()) if (map_dir / "run.json").exists() else {}
    published = figure(reports["source"], "published")
    drops = stage_drops(reports)
    known = [v for v in drops.values() if v is not None]
    dropped = sum(known) if len(known) == len(drops) else None
    in_map = run.get("frames_in_map", figure(reports["fusion"], "frames_in_map"))
    # Frames no stage counted as dropped but that never reached the map (lost in transit,
    # or published before a subscriber was ready) count against the rate too.
    lost = None if published is None or in_map is None or dropped is None else max(int(published) - dropped - int(in_map), 0)
    # Buffers hide a slow stage for a while: the map must also have kept the source's pace.
    fused_s = run.get("fused_seconds")
    pace = (int(in_map) - 1) / fused_s if in_map and fused_s else None
    kept_pace = pace is not None and pace >= PACE_SHARE * rate_hz
    keyframes = figure(reports["tracker"], "keyframes")
    kf_ok = keyframes is not None and kept_up(keyframes, PACE_SHARE)
    return {
        "rate_hz": float(rate_hz),
        "published": published,
        "dropped": dropped,
        "drops": drops,
        "frames_in_map": in_map,
        "lost": lost,
        "fused_hz": None if pace is None else round(pace, 4),
        "keyframes": keyframes,
        "keyframes_kept_up": kf_ok,
    }, bool(published) and dropped == 0 and lost == 0 and kept_pace and kf_ok


def search_rate(trial: Callable[[float], dict[str, Any]], start_hz: float, trials: int) -> tuple[float | None, list[dict[str, Any]]]:
    """The highest sustained rate found in ``trials`` trials, starting at ``start_hz``."""
    lo: float | None = None  # highest sustained
    hi: float | None = None  # lowest failed
    rate = max(float(start_hz), MIN_RATE_HZ)
    done: list[dict[str, Any]] = []
    for _ in range(max(trials, 1)):
        res = trial(round_rate(rate))
        done.append(res)
        if res["sustained"]:
            lo = rate if lo is None else max(lo, rate)
        else:
            hi = rate if hi is None else min(hi, rate)
        if lo is not None and hi is not None:
            rate = (lo + hi) / 2
        elif lo is not None:
            rate = lo * 2
        else:
            rate = hi / 2  # type: ignore[operator]
    best = max((r["rate_hz"] for r in done if r["sustained"]), default=None)
    return best, done


MIN_RATE_HZ = 0.001
"""The slowest rate tried: the paper's models on a CPU manage a few hundredths of a hertz."""


def round_rate(rate: float) -> float:
    """Three significant digits: 12.3, 0.0456."""
    return float(f"{max(rate, MIN_RATE_HZ):.3g}")
