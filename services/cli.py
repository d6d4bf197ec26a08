"""The ``trackgraph`` command: one entry point, one subcommand per job.

Every subcommand exits non-zero on failure with a one-line reason on stderr
(docs/architecture.md, "Command-line contract").
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)


class CommandError(Exception):
    """A command failed for a reason the user can act on; printed as one line."""


def _cmd_router(args: argparse.Namespace) -> int:
    from services.router import run_router
    from shared.config import TransportConfig, load_config

    if args.config:
        cfg = load_config(args.config).transport.model_copy(update={"mode": "router"})
    else:
        cfg = TransportConfig(mode="router", connect=[], listen=args.listen or ["tcp/127.0.0.1:7447"])
    if args.listen:
        cfg = cfg.model_copy(update={"listen": args.listen})
    if args.zenoh_config:
        cfg = cfg.model_copy(update={"zenoh_config_file": args.zenoh_config})
    cfg = TransportConfig.model_validate(cfg.model_dump())
    run_router(cfg)
    return 0


def _cmd_config_show(args: argparse.Namespace) -> int:
    from shared.config import dump_yaml, load_config

    cfg = load_config(args.path)
    if args.json:
        print(json.dumps(cfg.model_dump(mode="json"), indent=2))
    else:
        print(dump_yaml(cfg), end="")
    return 0


def _cmd_config_check(args: argparse.Namespace) -> int:
    from shared.config import load_config

    load_config(args.path)
    print(f"ok: {args.path}")
    return 0


def _load_or_default(path: Path | None):
    from shared.config import TrackGraphConfig, load_config

    return load_config(path) if path else TrackGraphConfig()


def _cmd_synth(args: argparse.Namespace) -> int:
    from shared.synth import run_synth

    if args.drift is not None:
        from shared.synth.drift import validate_rate

        try:
            validate_rate(args.drift)  # before the minutes of rendering, not after
        except ValueError as exc:
            raise CommandError(f"--drift: {exc}") from None
    result = run_synth(args.preset, args.seed, args.out, overwrite=args.overwrite, drift=args.drift)
    if args.rosbag is not None:
        from shared.ros2.bagio import write_sequence_bag

        bag = args.rosbag if args.rosbag.is_absolute() or args.rosbag.parent != Path(".") else Path(result["out"]) / args.rosbag
        result["rosbag"] = str(write_sequence_bag(Path(result["out"]), bag, overwrite=args.overwrite, progress=not args.json).path)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"wrote {result['frames']} frames with {result['objects']} objects to {result['out']}")
        print(f"  pictures: {Path(result['out']) / 'contact_sheet.png'}, {Path(result['out']) / 'topdown.png'}")
        if "rosbag" in result:
            print(f"  ROS 2 bag: {result['rosbag']}")
        if "drift" in result:
            out = Path(result["out"])
            print(f"  odometry drift {result['drift']:g} m/m: {out / 'traj.txt'} (drifted), {out / 'traj_gt.txt'} (true), "
                  f"{result['corrections']} corrections in {out / 'corrections.jsonl'}, picture {out / 'drift.png'}")
    return 0


def _cmd_source(args: argparse.Namespace) -> int:
    cfg = _load_or_default(args.config)
    if args.ros2:
        return _source_ros2(args, cfg)
    if args.sequence is None:
        raise CommandError("source: give SEQ_DIR (a sequence to replay), or --ros2 for a live robot's topics")
    live_only = [f for f in ("convention", "domain", "seconds") if getattr(args, f) is not None]
    if live_only:
        raise CommandError(f"source: --{live_only[0]} is for --ros2 (a live robot), not for replaying {args.sequence}")
    from services.source.node import run_source

    src = cfg.source.model_dump()
    for key in ("dataset", "mode", "stride", "max_frames"):
        if getattr(args, key) is not None:
            src[key] = getattr(args, key)
    if args.rate is not None:
        src["rate_hz"] = args.rate
    if args.corrections is not None:
        src["corrections"] = str(_corrections_file(args.corrections))
    update = {"source": type(cfg.source).model_validate(src)}
    if args.connect:
        update["transport"] = cfg.transport.model_copy(update={"connect": args.connect})
    cfg = type(cfg).model_validate({**cfg.model_dump(), **{k: v.model_dump() for k, v in update.items()}})
    stats = run_source(cfg, args.sequence, wait_subscribers_s=args.wait, status_file=args.status_file)
    out = {"published": stats.published, "dropped": stats.dropped, "seconds": round(stats.seconds, 3)}
    print(json.dumps(out) if args.json else f"published {stats.published} frames, dropped {stats.dropped}, in {stats.seconds:.1f} s")
    return 0


def _with_ros2(cfg, args: argparse.Namespace):
    """``cfg`` with the ROS 2 command-line overrides (--connect, --convention, --domain)."""
    data = cfg.model_dump()
    if args.connect:
        data["transport"]["connect"] = args.connect
    if getattr(args, "convention", None):
        data["ros2"]["link"]["convention"] = args.convention
    if getattr(args, "domain", None) is not None:
        data["ros2"]["link"]["domain_id"] = args.domain
    from shared.config.base import validate

    return validate(type(cfg), data, "command line")


def _source_ros2(args: argparse.Namespace, cfg) -> int:
    from services.ros2.node import run_ros2_source

    if args.sequence is not None:
        raise CommandError("source --ros2 takes its frames from the robot's topics: drop SEQ_DIR")
    bad = [f for f in ("dataset", "mode", "stride", "max_frames", "rate") if getattr(args, f) is not None]
    if bad:
        raise CommandError(f"source --ros2: --{bad[0].replace('_', '-')} is for replaying a sequence (set ros2.input in the config)")
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise CommandError(f"source --ros2: --seconds must be a positive number of seconds, got {args.seconds}")
    cfg = _with_ros2(cfg, args)
    stats = run_ros2_source(cfg, status_file=args.status_file, max_seconds=args.seconds)
    out = {"published": stats.published, "dropped": stats.dropped, "seconds": stats.seconds, "received": stats.received, "rejected": stats.rejected, "error": stats.error}
    print(json.dumps(out) if args.json else f"published {stats.published} frames, dropped {stats.dropped}, in {stats.seconds:.1f} s; rejected {stats.rejected or 'none'}")
    return 0


def _cmd_ros2_play(args: argparse.Namespace) -> int:
    from services.ros2.node import play_bag
    from shared.ros2.bagio import BagError

    cfg = _with_ros2(_load_or_default(args.config), args)
    try:
        stats = play_bag(args.bag, cfg, rate=args.rate, topics=args.topic, wait_subscribers_s=args.wait, progress=not args.json)
    except (BagError, ValueError) as e:
        raise CommandError(str(e)) from None
    out = {"messages": stats.messages, "topics": stats.topics, "seconds": stats.seconds, "late_s": stats.late_s}
    print(json.dumps(out) if args.json else f"played {stats.messages} messages on {len(stats.topics)} topics in {stats.seconds:.1f} s (at most {stats.late_s:.3f} s late)")
    return 0


def _cmd_ros2_bag(args: argparse.Namespace) -> int:
    from shared.ros2.bagio import BagError, write_sequence_bag

    try:
        # The writer replaces only a bag (a folder with metadata.yaml), and only once the new
        # one is complete: a failed run keeps the old bag, and no other folder is ever deleted.
        summary = write_sequence_bag(args.sequence, args.out, distro=args.distro, rate_hz=args.rate, compressed_rgb=args.compressed,
                                     overwrite=args.overwrite, progress=not args.json)  # fmt: skip
    except BagError as e:
        raise CommandError(str(e)) from None
    except ValueError as e:
        raise CommandError(f"ros2 bag: {e}".replace("rate_hz", "--rate")) from None
    out = {"out": str(summary.path), "frames": summary.frames, "seconds": summary.seconds, "topics": {t: list(v) for t, v in summary.topics.items()}}
    print(json.dumps(out) if args.json else f"wrote {summary.frames} frames ({summary.seconds:.1f} s) as a ROS 2 bag to {summary.path}")
    return 0


def _corrections_file(path: Path) -> Path:
    """A corrections file that reads (every line a valid PoseCorrection), or a one-line reason."""
    from shared.messages.poses import CorrectionsFileError, read_corrections

    try:
        read_corrections(path)
    except CorrectionsFileError as e:
        raise CommandError(str(e)) from None
    return path.resolve()


def _cmd_map(args: argparse.Namespace) -> int:
    from services.mapping import run_map

    cfg = _load_or_default(args.config)
    corrections = None if args.corrections is None else _corrections_file(args.corrections)
    summary = run_map(
        args.sequence, cfg, args.out, dataset=args.dataset, save_tracks=args.save_tracks,
        stride=args.stride, max_frames=args.max_frames, progress=not args.json, corrections=corrections,
    )  # fmt: skip
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"mapped {summary['frames']} frames in {summary['seconds']:.1f} s ({summary['hz']:.2f} Hz), "
            f"{summary['segments']} segments, peak RSS {summary['peak_rss_mb']:.0f} MB -> {args.out}"
        )
    return 0


def _print_metrics(result: dict, as_json: bool, keys: list[str]) -> None:
    if as_json:
        print(json.dumps(result))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(show_header=True, header_style="bold")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for k in keys:
        v = result.get(k)
        table.add_row(k, "n/a" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v)))
    Console().print(table)


def _cmd_eval_openlex3d(args: argparse.Namespace) -> int:
    from shared.eval import eval_openlex3d

    if args.pred is None and not args.oracle:
        raise CommandError("give --pred MAP_DIR, or --oracle to score the ground truth itself")
    if not 0 < args.alignment_threshold < float("inf"):  # also refuses NaN
        raise CommandError(f"--alignment-threshold must be a positive squared distance in m², got {args.alignment_threshold}")
    encoder = None
    if args.pred is not None and not args.oracle and (Path(args.pred) / "config.yaml").is_file():
        from services.query.offline import map_text_encoder

        encoder = map_text_encoder(Path(args.pred))  # a CLIP map is scored in CLIP's space
    result = eval_openlex3d(
        args.pred, args.gt, oracle=args.oracle, top_n=args.top_n, encoder=encoder,
        alignment=args.alignment, alignment_threshold=args.alignment_threshold,
    )  # fmt: skip
    keys = ["synonyms", "depictions", "vis_sim", "clutter", "missing", "incorrect", "ap", "ap50", "ap25", "top1_hit_rate"]
    _print_metrics(result, args.json, keys)
    return 0


def _cmd_eval_instances(args: argparse.Namespace) -> int:
    from shared.eval import eval_instances

    _print_metrics(eval_instances(args.pred, args.gt), args.json, ["ap", "ap50", "ap25", "segments_per_object"])
    return 0


def _cmd_eval_rooms(args: argparse.Namespace) -> int:
    from shared.eval.rooms import eval_rooms

    if not 0 < args.iou <= 1:
        raise CommandError(f"--iou must be in (0, 1], got {args.iou}")
    rank = None
    if (Path(args.pred) / "graph").is_dir():
        from services.query.core import QueryError
        from services.query.roomtypes import map_room_ranker

        try:
            rank = map_room_ranker(args.pred)
        except QueryError as exc:
            raise CommandError(f"{args.pred}: the room-type queries cannot run: {exc}") from None
    result = eval_rooms(args.pred, args.gt, iou=args.iou, rank_rooms=rank)
    keys = ["precision", "recall", "f1", "n_pred", "n_gt", "over_segmented", "under_segmented", "mean_iou", "type_accuracy", "room_type_top1"]
    _print_metrics(result, args.json, keys)
    if not args.json:
        from rich.console import Console
        from rich.table import Table

        table = Table(show_header=True, header_style="bold", title=f"ground-truth rooms (match at IoU >= {args.iou:g})")
        for col in ("room", "type", "best predicted", "IoU", "matched"):
            table.add_column(col, justify="right" if col in ("IoU", "best predicted") else "left")
        for r in result["per_room"]:
            best = "none" if r["best_pred_id"] is None else f"{r['best_pred_id']}" + (f" ({r['best_pred_name']})" if r["best_pred_name"] else "")
            table.add_row(r["gt_name"], r["gt_type"], best, f"{r['iou']:.3f}", "no" if r["matched_pred_id"] is None else "yes")
        Console().print(table)
        if result["room_queries"]:
            table = Table(show_header=True, header_style="bold", title='"which room is X": the top room for each ground-truth type')
            for col in ("query", "top room", "its ground-truth room", "hit"):
                table.add_column(col)
            for q in result["room_queries"]:
                top = "none" if q["top_room"] is None else f"{q['top_room']}" + (f" ({q['top_name']})" if q["top_name"] else "")
                table.add_row(q["query"], top, "unmatched" if q["gt_room"] is None else f"{q['gt_room']} ({q['gt_type']})", "yes" if q["hit"] else "no")
            Console().print(table)
    return 0


def _cmd_eval_tracking(args: argparse.Namespace) -> int:
    from shared.eval import eval_tracking

    keys = ["mean_iou", "idf1", "id_switches_per_100_frames_per_object", "fragmentations"]
    _print_metrics(eval_tracking(args.pred, args.gt), args.json, keys)
    return 0


def _cmd_eval_queries(args: argparse.Namespace) -> int:
    from services.query.evaluate import eval_queries

    result = eval_queries(args.pred, args.gt, min_size_m=args.min_size, gallery=args.gallery, details=args.json)
    _print_metrics(result, args.json, ["top1_hit_rate", "n_hits", "n_queries", "min_size_m", "gallery"])
    return 0


def _cmd_eval_segmenter(args: argparse.Namespace) -> int:
    from services.keyframe_vl.evaluate import eval_segmenter

    result = eval_segmenter(args.seq, _load_or_default(args.config), every=args.every)
    if not args.json:
        result = {k: v for k, v in result.items() if k != "per_keyframe"}
    _print_metrics(result, args.json, ["mean_best_iou", "objects", "keyframes", "ms_per_keyframe"])
    return 0


def _cmd_models_check(args: argparse.Namespace) -> int:
    from services.models.check import check_models

    result = check_models(_load_or_default(args.config), load=not args.no_load)
    if args.json:
        print(json.dumps(result))
    else:
        if not result["models"]:
            print("this config needs no weight files")
        for m in result["models"]:
            state = "ok" if m["loads"] else ("present" if m["present"] and m["loads"] is None else "MISSING" if not m["present"] else "FAILS")
            # The absolute path: a relative one is read from wherever the command runs.
            print(f"{m['role']:<15} {m['backend']:<13} {state:<8} {m.get('resolved') or m['path']}")
            if m.get("loader"):
                print(f"{'':<15} loader: {m['loader']}")
            if m["error"]:
                print(f"{'':<15} {m['error']}")
            # A file that fails to load is as good as missing: say where the right one is.
            if not m["present"] or m["loads"] is False:
                print(f"{'':<15} get it: {m['source']}")
    return 0 if result["ok"] else 1


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    from services.models.export import export_all

    only = set(args.only) if args.only else None
    for role, path in export_all(_load_or_default(args.config), args.out, only, fastsam_static=args.fastsam_static).items():
        print(f"{role}: {path}")
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    from services.serve import serve

    cfg = _load_or_default(args.config)
    if args.connect:
        data = cfg.model_dump()
        data["transport"]["connect"] = args.connect
        cfg = type(cfg).model_validate(data)
    if args.sequence is not None:
        from services.mapping import prepare_config

        cfg = prepare_config(cfg, args.sequence)
    serve(args.service, cfg, out=args.out, resume=args.resume, exit_at_end=args.exit_at_end, status_file=args.status_file)
    return 0


def _query_request(args: argparse.Namespace, text: str | None):
    import numpy as np

    from shared.messages.rpc import QueryRequest

    image = None
    if args.image is not None:
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(args.image) as im:
                image = np.asarray(im.convert("RGB"))
        except (OSError, UnidentifiedImageError) as exc:
            raise CommandError(f"{args.image}: not a readable image ({exc})") from None
    if (text is None) == (image is None):
        raise CommandError("give a query TEXT or --image FILE (one of them)")
    if (args.near is None) != (args.radius is None):
        raise CommandError("--near X Y Z and --radius R go together")
    if args.in_room is not None and args.room is not None:
        raise CommandError("--in-room TEXT and --room ID both choose the room: give one of them")
    if args.rooms and args.in_room is not None:
        raise CommandError("--in-room TEXT filters segments; --rooms ranks the rooms themselves: give one of them")
    try:
        return QueryRequest(
            text=text, image=image, top_k=args.top_k, room=args.room, room_text=args.in_room, radius=args.radius,
            gallery=args.gallery, center=None if args.near is None else np.asarray(args.near, np.float64),
            target="rooms" if args.rooms else "segments",
        )  # fmt: skip
    except ValueError as exc:
        raise CommandError(f"bad query: {'; '.join(str(exc).splitlines()[:2])}") from None


def _print_ranked(rows: list[dict], cells: list[list[str]], as_json: bool, title: str, columns: tuple[str, ...], left: tuple[str, ...], empty: str) -> None:
    """``rows`` as the ``--json`` list, or a rich table of ``cells`` under ``columns`` (those in
    ``left`` left-aligned), or ``empty`` when there are none."""
    if as_json:
        print(json.dumps(rows))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, show_header=True, header_style="bold")
    for col in columns:
        table.add_column(col, justify="left" if col in left else "right")
    for row in cells:
        table.add_row(*row)
    Console().print(table if cells else f"{title}: {empty}")


def _centroid(r: dict) -> str:
    return " ".join(f"{v:+.2f}" for v in r["centroid"])


def _print_hits(hits, as_json: bool, title: str) -> None:
    from services.query.core import hit_rows

    rows = hit_rows(hits)
    cells = [
        [
            str(i), str(h.segment), f"{h.score:.3f}", _centroid(r), " x ".join(f"{v:.2f}" for v in (h.bbox_max - h.bbox_min).tolist()),
            "-" if h.room is None else str(h.room), "-" if h.best_track is None else str(h.best_track),
        ]
        for i, (h, r) in enumerate(zip(hits, rows, strict=True), 1)
    ]  # fmt: skip
    columns = ("rank", "segment", "score", "centroid (m)", "size (m)", "room", "best track")
    _print_ranked(rows, cells, as_json, title, columns, ("centroid (m)", "size (m)"), "no segments")


def _print_rooms(rooms, as_json: bool, title: str) -> None:
    from services.query.core import room_rows

    rows = room_rows(rooms)
    cells = [
        [
            str(i), str(h.room), h.name or "-", f"{h.score:.3f}", "-" if h.margin is None else f"{h.margin:+.3f}", _centroid(r),
            "-" if r["bbox"] is None else " x ".join(f"{b - a:.2f}" for a, b in zip(*r["bbox"], strict=True)),
        ]
        for i, (h, r) in enumerate(zip(rooms, rows, strict=True), 1)
    ]  # fmt: skip
    columns = ("rank", "room", "name", "score", "margin", "centroid (m)", "size (m)")
    _print_ranked(rows, cells, as_json, title, columns, ("name", "centroid (m)", "size (m)"), "no room has a feature yet")


def _chosen_room(rooms) -> str:
    """``room N (name, score)`` of the room a ``--in-room`` query took (the best-ranked)."""
    best = rooms[0]
    return f"room {best.room} ({best.name or 'unnamed'}, {best.score:.3f})"


def _cmd_query(args: argparse.Namespace) -> int:
    pos = list(args.args)
    if args.live:
        if len(pos) > 1:
            raise CommandError(f"--live takes one query TEXT, got {len(pos)} arguments")
        text = pos[0] if pos else None
        if args.timeout is not None and not args.timeout > 0:
            raise CommandError(f"--timeout must be a positive number of seconds, got {args.timeout}")
        req = _query_request(args, text)
        from services.query.client import QueryClient

        cfg = _load_or_default(args.config)
        transport = cfg.transport
        if args.connect:
            transport = transport.model_copy(update={"connect": args.connect})
        with QueryClient(transport, robot_id=args.robot or cfg.robot_id, timeout_s=args.timeout) as client:
            reply = client.ask(req)
        where = f"live, graph version {reply.graph_seq}"
    else:
        if not pos or len(pos) > 2:
            raise CommandError('give MAP_DIR and a query TEXT (or MAP_DIR --image FILE), or --live "TEXT"')
        map_dir, text = Path(pos[0]), (pos[1] if len(pos) > 1 else None)
        if not map_dir.is_dir():
            raise CommandError(f"{map_dir}: no such map folder (for a running system use --live)")
        req = _query_request(args, text)
        from services.query.core import QueryError
        from services.query.offline import OfflineQueries, map_config

        try:
            reply = OfflineQueries(map_dir, map_config(map_dir, args.config)).ask(req)
        except QueryError as exc:
            raise CommandError(str(exc)) from None
        where = str(map_dir)
    if reply.error is not None:
        raise CommandError(f"query refused: {reply.error}")
    title = f"{text or args.image} ({where})"
    if args.rooms:
        _print_rooms(reply.rooms, args.json, title)
        return 0
    if args.in_room is not None and reply.rooms:
        chosen = _chosen_room(reply.rooms)
        if args.json:
            # stdout stays the contract's list of hit rows; which room was taken goes to the log.
            log.info("--in-room %r: %s", args.in_room, chosen)
        else:
            print(f"in {chosen}")
    _print_hits(reply.hits, args.json, title)
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from shared.graph.store import MapStore

    map_dir = args.map_dir
    if not (map_dir / "graph").is_dir():
        raise CommandError(f"{map_dir}: no graph/ folder (is it a trackgraph map folder?)")
    queries = {}
    if args.query:
        from services.query.core import QueryError
        from services.query.offline import OfflineQueries, map_config
        from shared.messages.rpc import QueryRequest

        try:
            offline = OfflineQueries(map_dir, map_config(map_dir, args.config))
        except QueryError as exc:
            raise CommandError(str(exc)) from None
        for text in args.query:
            reply = offline.ask(QueryRequest(text=text, top_k=args.top_k))
            if reply.error is not None:
                raise CommandError(f"query {text!r} refused: {reply.error}")
            queries[text] = reply.hits
    from services.viewer.recording import write_map_recording

    out = args.out or map_dir / "map.rrd"
    try:
        write_map_recording(map_dir, out, queries=queries, sequence_dir=args.sequence, max_frames=args.frames)
    except FileNotFoundError as exc:
        raise CommandError(str(exc)) from None
    print(f"wrote {out}  (open it with: rerun {out})")
    if args.png is not None:
        import numpy as np

        from services.viewer.render import render_map_pictures

        state = MapStore(map_dir / "graph").load()
        traj = np.asarray(state.extra.get("trajectory", np.zeros((0, 3))))
        for path in render_map_pictures(state.snapshot, args.png, queries, traj):
            print(f"wrote {path}")
    if args.open:
        import shutil

        viewer = shutil.which("rerun")
        if viewer is None:
            raise CommandError("the rerun viewer is not on PATH (pip install rerun-sdk gives it)")
        os.execv(viewer, [viewer, str(out)])
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from services.demo import run_demo
    from services.launch import LaunchError

    try:
        r = run_demo(args.out, preset=args.preset, seed=args.seed, config=args.config)
    except LaunchError as exc:
        raise CommandError(f"the demo's launch failed: {exc}") from None
    if args.json:
        print(json.dumps(r))
        return 0
    m = r["metrics"]
    print(f"perception: {r['perception']}")
    print(f"mapped {r['frames']} frames as separate processes in {r['timings'].get('distributed_map_s', 0):.0f} s: {r['segments']} segments")
    for q in r["queries"]:
        top = q["hits"][0] if q["hits"] else None
        print(f"  {q['query']!r:<28} {q['ms']:6.0f} ms  -> " + (f"segment {top['segment']} ({top['object']}, IoU {top['iou']:.2f})" if top else "no hit"))
    print(f"instance AP50 {m['ap50']:.3f}, top-1 hits of synonym queries over 20 cm {m['top1_synonym_queries_over_20cm']:.3f}, synonyms {m['synonyms']:.3f}")
    for what, path in r["files"].items():
        print(f"{what:<15} {path}")
    return 0


def _cmd_bench_run(args: argparse.Namespace) -> int:
    from services.bench.core import run_bench
    from services.bench.runs import BenchError

    if (args.preset is None) == (args.sequence is None):
        raise CommandError("give either --preset small|demo|revisit or --sequence SEQ_DIR --gt GT_DIR")
    if args.sequence is not None and not args.config:
        raise CommandError("--sequence needs at least one --config FILE (simulated perception works on synthetic scenes only)")
    if args.rate_seconds is not None and args.rate_seconds <= 0:
        raise CommandError(f"--rate-seconds must be positive, got {args.rate_seconds}")
    try:
        res = run_bench(
            args.out, preset=args.preset, seed=args.seed, sequence=args.sequence, gt=args.gt, configs=args.config or [],
            dataset=args.dataset, max_frames=args.max_frames, rate_trials=args.rate_trials, rate_frames=args.rate_frames,
            rate_seconds=args.rate_seconds, random_weights=args.random_weights, resume=args.resume, progress=not args.json,
        )  # fmt: skip
    except BenchError as exc:
        raise CommandError(str(exc)) from None
    if args.json:
        print(json.dumps({"out": str(args.out), "markdown": str(Path(args.out) / "bench.md"), "json": str(Path(args.out) / "bench.json"), "plots": res["plots"], "seconds": res["seconds"]}))
    else:
        print((Path(args.out) / "bench.md").read_text())
        print(f"tables: {Path(args.out) / 'bench.md'}, JSON: {Path(args.out) / 'bench.json'}, plots: {Path(args.out) / 'plots'}")
    return 0


def _cmd_launch(args: argparse.Namespace) -> int:
    from services.launch import LaunchError, run_launch

    try:
        summary = run_launch(args.file, sequence=args.sequence, out=args.out, log_dir=args.log_dir, status=not args.json)
    except LaunchError as exc:
        raise CommandError(str(exc)) from None
    if args.json:
        print(json.dumps(summary))
    else:
        for name, s in summary["services"].items():
            print(f"{name:<12} {s['state']:<9} restarts {s['restarts']}  log {s['log']}")
    return 0


def _cmd_status(args: argparse.Namespace) -> int:
    from services.monitor import MonitorError, run_status

    cfg = _load_or_default(args.config)
    transport = cfg.transport
    if args.connect:
        transport = transport.model_copy(update={"connect": args.connect})
    try:
        return run_status(transport, args.robot or cfg.robot_id, once=args.once, as_json=args.json, timeout=args.timeout)
    except MonitorError as exc:
        raise CommandError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="trackgraph", description=__doc__.splitlines()[0])
    p.add_argument("-v", "--verbose", action="count", default=0, help="debug logging")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("router", help="run a Zenoh router (no separate binary needed)")
    r.add_argument("--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447 (repeatable; default tcp/127.0.0.1:7447)")
    r.add_argument("--config", metavar="FILE", help="take the transport section of this system config")
    r.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 file (TLS, users, access control)")
    r.set_defaults(func=_cmd_router)

    sy = sub.add_parser("synth", help="generate a synthetic RGB-D sequence with ground truth")
    sy.add_argument("--preset", choices=["small", "demo", "revisit"], default="small")
    sy.add_argument("--seed", type=int, default=0)
    sy.add_argument("--out", type=Path, required=True, metavar="DIR")
    sy.add_argument("--overwrite", action="store_true", help="replace a non-empty DIR")
    sy.add_argument("--rosbag", type=Path, metavar="BAG", help="also write the sequence as a ROS 2 bag (images, CameraInfo, TF); a bare name goes inside DIR")
    sy.add_argument("--drift", type=float, metavar="RATE",
                    help="odometry drift in metres per metre travelled (0 < RATE <= 0.5): writes traj.txt drifted, "
                         "the true poses to traj_gt.txt and the loop-closure corrections to corrections.jsonl")
    sy.add_argument("--json", action="store_true", help='print {"frames", "objects", "out"} (and "rosbag" with --rosbag, '
                                                        '"drift" and "corrections" with --drift)')
    sy.set_defaults(func=_cmd_synth)

    so = sub.add_parser("source", help="replay a sequence as frames over Zenoh, or with --ros2 take a live robot's ROS 2 topics")
    so.add_argument("sequence", type=Path, metavar="SEQ_DIR", nargs="?")
    so.add_argument("--ros2", action="store_true", help="frames from the robot's ROS 2 camera and pose topics (config section ros2) until Ctrl-C")
    so.add_argument("--convention", choices=["rmw_zenoh", "bridge"], help="--ros2: the ROS 2 key convention (default: the config's)")
    so.add_argument("--domain", type=int, metavar="ID", help="--ros2: ROS_DOMAIN_ID (default: the config's)")
    so.add_argument("--seconds", type=float, metavar="S", help="--ros2: stop after S seconds")
    so.add_argument("--config", type=Path, metavar="FILE")
    so.add_argument("--dataset", choices=["replica", "scannetpp", "hm3d", "tum", "rosbag"])
    so.add_argument("--mode", choices=["lossless", "live"])
    so.add_argument("--rate", type=float, metavar="HZ", help="live-mode rate")
    so.add_argument("--stride", type=int, metavar="N")
    so.add_argument("--max-frames", type=int, metavar="N")
    so.add_argument("--corrections", type=Path, metavar="FILE", help="pose corrections (JSON lines) to send on poses/correction as the replay passes their frames")
    so.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    so.add_argument("--wait", type=float, default=30.0, metavar="S", help="lossless: wait this long for a subscriber")
    so.add_argument("--status-file", type=Path, metavar="FILE", help="write the last ServiceStatus report here as JSON at stop")
    so.add_argument("--json", action="store_true", help='print {"published", "dropped", "seconds"} (--ros2 adds "received", "rejected", "error")')
    so.set_defaults(func=_cmd_source)

    mp = sub.add_parser("map", help="map a recorded sequence in-process (no Zenoh)")
    mp.add_argument("sequence", type=Path, metavar="SEQ_DIR")
    mp.add_argument("--config", type=Path, metavar="FILE", help="system config (default: the paper's settings)")
    mp.add_argument("--out", type=Path, required=True, metavar="MAP_DIR")
    mp.add_argument("--dataset", choices=["replica", "scannetpp", "hm3d", "tum", "rosbag"])
    mp.add_argument("--save-tracks", action="store_true", help="write per-frame track maps for eval tracking")
    mp.add_argument("--stride", type=int, metavar="N")
    mp.add_argument("--max-frames", type=int, metavar="N")
    mp.add_argument("--corrections", type=Path, metavar="FILE",
                    help="pose corrections (JSON lines, e.g. a drifting synth's corrections.jsonl), each applied when the map reaches its frame")
    mp.add_argument("--json", action="store_true", help='print {"frames", "seconds", "hz", "peak_rss_mb", "segments", "corrections"}')
    mp.set_defaults(func=_cmd_map)

    ev = sub.add_parser("eval", help="evaluate maps, tracks and masks against ground truth")
    evsub = ev.add_subparsers(dest="eval_command", required=True, metavar="WHAT")
    ol = evsub.add_parser("openlex3d", help="OpenLex3D top-N categories and retrieval AP")
    ol.add_argument("--pred", type=Path, metavar="MAP_DIR", help="map in the OpenLex3D prediction format")
    ol.add_argument("--gt", type=Path, required=True, metavar="GT_DIR")
    ol.add_argument("--oracle", action="store_true", help="score the ground truth itself (upper bound)")
    ol.add_argument("--top-n", type=int, default=5, metavar="N")
    ol.add_argument(
        "--alignment", choices=["per_mask", "global"], default="per_mask",
        help="retrieval mask alignment: per_mask (OpenLex3D's default: a point joins every instance "
        "within the threshold) or global (the instance of its nearest predicted point)",
    )  # fmt: skip
    ol.add_argument(
        "--alignment-threshold", type=float, default=0.001, metavar="D2",
        help="alignment threshold on the SQUARED distance in m² (default 0.001, OpenLex3D's: 3.16 cm)",
    )  # fmt: skip
    ol.add_argument("--json", action="store_true")
    ol.set_defaults(func=_cmd_eval_openlex3d)
    ins = evsub.add_parser("instances", help="class-agnostic 3D instance AP and duplicates")
    ins.add_argument("--pred", type=Path, required=True, metavar="MAP_DIR")
    ins.add_argument("--gt", type=Path, required=True, metavar="GT_DIR")
    ins.add_argument("--json", action="store_true")
    ins.set_defaults(func=_cmd_eval_instances)
    rm = evsub.add_parser("rooms", help="room segmentation (needs MAP_DIR/rooms.npz): precision, recall, F1 and IoU per room")
    rm.add_argument("--pred", type=Path, required=True, metavar="MAP_DIR")
    rm.add_argument("--gt", type=Path, required=True, metavar="GT_DIR")
    rm.add_argument("--iou", type=float, default=0.5, metavar="T", help="IoU at which a predicted room matches a ground-truth room")
    rm.add_argument("--json", action="store_true", help='print {"precision", "recall", "f1", "mean_iou", "type_accuracy", ..., "per_room"}')
    rm.set_defaults(func=_cmd_eval_rooms)
    tr = evsub.add_parser("tracking", help="2D source-track quality (needs map --save-tracks)")
    tr.add_argument("--pred", type=Path, required=True, metavar="MAP_DIR")
    tr.add_argument("--gt", type=Path, required=True, metavar="SEQ_DIR")
    tr.add_argument("--json", action="store_true")
    tr.set_defaults(func=_cmd_eval_tracking)

    qe = evsub.add_parser("queries", help="top-1 hits of the query service's answers (eq. 10) for the ground truth's synonym queries")
    qe.add_argument("--pred", type=Path, required=True, metavar="MAP_DIR")
    qe.add_argument("--gt", type=Path, required=True, metavar="GT_DIR")
    qe.add_argument("--min-size", type=float, default=0.2, metavar="M", help="only queries for objects larger than this (m)")
    qe.add_argument("--gallery", choices=["max", "mean"], help="override the map config's gallery scoring")
    qe.add_argument("--json", action="store_true", help='print {"top1_hit_rate", "n_hits", "n_queries", ..., "per_query"}')
    qe.set_defaults(func=_cmd_eval_queries)

    sg = evsub.add_parser("segmenter", help="per-keyframe mask quality against ground-truth instances")
    sg.add_argument("--seq", type=Path, required=True, metavar="SEQ_DIR")
    sg.add_argument("--config", type=Path, metavar="FILE")
    sg.add_argument("--every", type=int, metavar="N", help="segment every Nth frame (default K_f)")
    sg.add_argument("--json", action="store_true", help='print {"mean_best_iou", "objects", ...}')
    sg.set_defaults(func=_cmd_eval_segmenter)

    mo = sub.add_parser("models", help="weight files a config needs")
    mosub = mo.add_subparsers(dest="models_command", required=True, metavar="ACTION")
    mc = mosub.add_parser("check", help="which weight files the config needs, whether present and loadable, where to get them")
    mc.add_argument("--config", type=Path, metavar="FILE")
    mc.add_argument("--no-load", action="store_true", help="only check that the files exist")
    mc.add_argument("--json", action="store_true", help='print {"ok", "missing": [...], "models": [...]}')
    mc.set_defaults(func=_cmd_models_check)

    ex = sub.add_parser("export-onnx", help="export the configured FastSAM, CLIP and DINOv3 to ONNX")
    ex.add_argument("--config", type=Path, required=True, metavar="FILE")
    ex.add_argument("--out", type=Path, required=True, metavar="DIR")
    ex.add_argument("--only", action="append", choices=["segmenter", "vl_encoder", "dense_features"])
    ex.add_argument(
        "--fastsam-static", action="store_true",
        help="fix FastSAM's input at imgsz x imgsz (default: dynamic, letterboxed like the .pt path; "
        "a static export's masks differ from the .pt path's on non-square frames)",
    )
    ex.set_defaults(func=_cmd_export_onnx)

    sv = sub.add_parser("serve", help="run one service as this process, until Ctrl-C")
    sv.add_argument("service", choices=["keyframe_vl", "tracker", "fusion", "query", "viewer", "ros2"])
    sv.add_argument("--config", type=Path, metavar="FILE")
    sv.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    sv.add_argument("--out", type=Path, metavar="PATH", help="fusion: the map folder (snapshots, final map); viewer: the .rrd recording")
    sv.add_argument("--resume", action="store_true", help="fusion: continue from the last snapshot in MAP_DIR")
    sv.add_argument("--exit-at-end", action="store_true", help="fusion: stop once the replayed sequence is mapped")
    sv.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="a synthetic sequence whose ground truth the simulated backends use")
    sv.add_argument("--status-file", type=Path, metavar="FILE", help="write the last ServiceStatus report here as JSON at stop")
    sv.set_defaults(func=_cmd_serve)

    vw = sub.add_parser("view", help="a Rerun recording (.rrd) of a saved map, optional query hits and PNG renders")
    vw.add_argument("map_dir", type=Path, metavar="MAP_DIR")
    vw.add_argument("--out", type=Path, metavar="FILE.rrd", help="default MAP_DIR/map.rrd")
    vw.add_argument("--query", action="append", metavar="TEXT", help="highlight this query's hits (repeatable)")
    vw.add_argument("--top-k", type=int, default=3, metavar="K", help="hits per query")
    vw.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="add tracked frames (needs map --save-tracks)")
    vw.add_argument("--frames", type=int, default=60, metavar="N", help="at most this many tracked frames")
    vw.add_argument("--png", type=Path, metavar="DIR", help="also render top-down PNGs of the map and of each query")
    vw.add_argument("--config", type=Path, metavar="FILE", help="the query encoder's config (default MAP_DIR/config.yaml)")
    vw.add_argument("--open", action="store_true", help="open the recording in the Rerun viewer")
    vw.set_defaults(func=_cmd_view)

    dm = sub.add_parser("demo", help="the synthetic demo scene through the whole distributed system, with example queries and a report")
    dm.add_argument("--out", type=Path, default=Path("demo_out"), metavar="DIR")
    dm.add_argument("--preset", choices=["small", "demo", "revisit"], default="demo")
    dm.add_argument("--seed", type=int, default=0)
    dm.add_argument("--config", type=Path, metavar="FILE", help="default: the paper's models if their weights are present, else simulated perception")
    dm.add_argument("--json", action="store_true", help="print the report's figures as JSON")
    dm.set_defaults(func=_cmd_demo)

    be = sub.add_parser("bench", help="the paper's tables for one sequence and one or more configs")
    besub = be.add_subparsers(dest="bench_cmd", required=True)
    br = besub.add_parser("run", help="segmentation, retrieval, efficiency, tracker and gallery ablations: markdown, JSON and plots")
    br.add_argument("--preset", choices=["small", "demo", "revisit"], help="a synthetic scene (generated into OUT)")
    br.add_argument("--seed", type=int, default=0, help="seed of the synthetic scene")
    br.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="a recorded sequence instead of a preset")
    br.add_argument("--gt", type=Path, metavar="GT_DIR", help="its OpenLex3D ground truth (with --sequence)")
    br.add_argument("--dataset", choices=["replica", "scannetpp", "hm3d", "tum", "rosbag"])
    br.add_argument("--config", type=Path, action="append", metavar="FILE", help="a system config (repeatable; default deploy/configs/synthetic.yaml)")
    br.add_argument("--out", type=Path, default=Path("bench_out"), metavar="DIR")
    br.add_argument("--max-frames", type=int, metavar="N", help="map only the first N frames")
    br.add_argument("--rate-trials", type=int, default=3, metavar="N", help="live runs per tracker mode in the input-rate search (0 skips it)")
    br.add_argument("--rate-frames", type=int, default=60, metavar="N", help="frames per live run")
    br.add_argument("--rate-seconds", type=float, metavar="S", help="instead: each live run sends frames for about S seconds (two keyframes at least)")
    br.add_argument("--resume", action="store_true", help="keep the maps an interrupted run of the same --out finished")
    br.add_argument("--random-weights", type=Path, metavar="DIR", help="run each config's models on random weights written to DIR: the real architectures' times and memory, meaningless maps")
    br.add_argument("--json", action="store_true", help='print {"out", "markdown", "json", "plots", "seconds"}')
    br.set_defaults(func=_cmd_bench_run)

    r2 = sub.add_parser("ros2", help="ROS 2 bags over Zenoh: play one as a robot would send it, or write a sequence as one")
    r2sub = r2.add_subparsers(dest="ros2_command", required=True, metavar="ACTION")
    pl = r2sub.add_parser("play", help="publish a ROS 2 bag's topics over Zenoh at the recorded pace (rmw_zenoh or bridge convention)")
    pl.add_argument("bag", type=Path, metavar="BAG")
    pl.add_argument("--config", type=Path, metavar="FILE", help="transport and the ros2.link section (default: rmw_zenoh, domain 0)")
    pl.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    pl.add_argument("--convention", choices=["rmw_zenoh", "bridge"])
    pl.add_argument("--domain", type=int, metavar="ID", help="ROS_DOMAIN_ID")
    pl.add_argument("--rate", type=float, default=1.0, metavar="R", help="play R times the recorded pace (as ros2 bag play --rate)")
    pl.add_argument("--topic", action="append", metavar="TOPIC", help="only these topics (repeatable; default all)")
    pl.add_argument("--wait", type=float, default=0.0, metavar="S", help="first wait up to S seconds for subscribers of the sensor_msgs topics (images, CameraInfo)")
    pl.add_argument("--json", action="store_true", help='print {"messages", "topics", "seconds", "late_s"}')
    pl.set_defaults(func=_cmd_ros2_play)
    bg = r2sub.add_parser("bag", help="write a sequence folder as a ROS 2 bag (colour, depth, CameraInfo, TF)")
    bg.add_argument("sequence", type=Path, metavar="SEQ_DIR")
    bg.add_argument("--out", type=Path, required=True, metavar="BAG")
    bg.add_argument("--distro", choices=["humble", "iron", "jazzy", "kilted"], default="jazzy", help="message definitions written into the bag")
    bg.add_argument("--rate", type=float, metavar="HZ", help="frame rate of the stamps (default the sequence's, else 30)")
    bg.add_argument("--compressed", action="store_true", help="colour as JPEG CompressedImage on .../compressed")
    bg.add_argument("--overwrite", action="store_true", help="replace an existing BAG")
    bg.add_argument("--json", action="store_true", help='print {"out", "frames", "seconds", "topics"}')
    bg.set_defaults(func=_cmd_ros2_bag)

    la = sub.add_parser("launch", help="start a router and every service of a launch file as separate processes")
    la.add_argument("file", type=Path, metavar="LAUNCH_FILE", help="e.g. deploy/local.yaml")
    la.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="what the source replays (overrides the file)")
    la.add_argument("--out", type=Path, metavar="MAP_DIR", help="fusion's map folder (overrides the file)")
    la.add_argument("--log-dir", type=Path, metavar="DIR", help="one log per process (default MAP_DIR/logs)")
    la.add_argument("--json", action="store_true", help="no status table; print the final summary as JSON")
    la.set_defaults(func=_cmd_launch)

    st = sub.add_parser("status", help="the live status table of a running system (every service's ServiceStatus reports)")
    st.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s) (default: the config's)")
    st.add_argument("--robot", metavar="ID", help="robot id (default: the config's)")
    st.add_argument("--config", type=Path, metavar="FILE", help="take transport and robot id from this system config")
    st.add_argument("--once", action="store_true", help="print the table once and exit")
    st.add_argument("--timeout", type=float, default=5.0, metavar="S", help="fail if no service reports within S seconds")
    st.add_argument("--json", action="store_true", help='JSON instead of the table: {"robot", "services": {NAME: {ServiceStatus fields..., "age_s", "summary"}}}, one line per second (once with --once)')
    st.set_defaults(func=_cmd_status)

    q = sub.add_parser("query", help='ranked segments (or with --rooms rooms) for a text or image query: MAP_DIR "TEXT", or --live "TEXT"')
    q.add_argument("args", nargs="*", metavar="[MAP_DIR] TEXT", help='a saved map and the query, or only the query with --live')
    q.add_argument("--live", action="store_true", help="ask the running query service over Zenoh")
    q.add_argument("--image", type=Path, metavar="FILE", help="an image query instead of text")
    q.add_argument("--top-k", type=int, metavar="K")
    q.add_argument("--room", type=int, metavar="ID", help="only segments in this room")
    q.add_argument("--in-room", metavar="TEXT", help='only segments in the room that best matches TEXT (e.g. "kitchen"); not with --room')
    q.add_argument("--rooms", action="store_true", help='rank the rooms instead of the segments ("which room is the kitchen")')
    q.add_argument("--near", type=float, nargs=3, metavar=("X", "Y", "Z"), help="only segments within --radius of this point")
    q.add_argument("--radius", type=float, metavar="M")
    q.add_argument("--gallery", choices=["max", "mean"], help="eq. 10 max over the gallery (default) or the mean feature")
    q.add_argument("--config", type=Path, metavar="FILE", help="offline: the encoder's config (default MAP_DIR/config.yaml); live: transport and robot id")
    q.add_argument("--connect", action="append", metavar="ENDPOINT", help="live: router endpoint(s)")
    q.add_argument("--robot", metavar="ID", help="live: robot id (default: the config's)")
    q.add_argument("--timeout", type=float, metavar="S", help="live: seconds to wait for the answer (the request's deadline is a little under it)")
    q.add_argument("--json", action="store_true", help='print [{"segment", "score", "centroid", "bbox", "room", "best_track"}]; with --rooms [{"room", "score", "margin", "name", "centroid", "bbox"}]')
    q.set_defaults(func=_cmd_query)

    c = sub.add_parser("config", help="inspect and validate config files")
    csub = c.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    show = csub.add_parser("show", help="print the resolved config, defaults included")
    show.add_argument("path", type=Path)
    show.add_argument("--json", action="store_true", help="JSON instead of YAML")
    show.set_defaults(func=_cmd_config_show)
    check = csub.add_parser("check", help="validate a config; non-zero exit names the bad key")
    check.add_argument("path", type=Path)
    check.set_defaults(func=_cmd_config_check)
    return p


def main(argv: list[str] | None = None) -> int:
    from shared.config import ConfigError
    from shared.datasets.base import DatasetError
    from shared.eval.errors import EvalInputError
    from shared.logs import setup_logging
    from shared.transport import TransportError

    args = build_parser().parse_args(argv)
    setup_logging(args.verbose)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (ConfigError, CommandError, DatasetError, EvalInputError, TransportError) as exc:
        print(f"trackgraph: error: {'; '.join(str(exc).splitlines())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # noqa: BLE001 - a one-line reason beats a traceback for users
        if args.verbose:
            raise
        print(f"trackgraph: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
