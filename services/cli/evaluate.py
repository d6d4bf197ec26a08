"""``trackgraph eval ...``: maps, tracks, rooms, queries and masks against ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import CommandError, _load_or_default, add_actions


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

    result = eval_segmenter(args.seq, _load_or_default(args.config, args.set), every=args.every)
    if not args.json:
        result = {k: v for k, v in result.items() if k != "per_keyframe"}
    _print_metrics(result, args.json, ["mean_best_iou", "objects", "keyframes", "ms_per_keyframe"])
    return 0


def _against_truth(evsub: argparse._SubParsersAction, name: str, help: str, gt: str = "GT_DIR") -> argparse.ArgumentParser:
    """An ``eval`` action that scores a map (``--pred MAP_DIR``) against ground truth (``--gt``)."""
    p = evsub.add_parser(name, help=help)
    p.add_argument("--pred", type=Path, required=True, metavar="MAP_DIR")
    p.add_argument("--gt", type=Path, required=True, metavar=gt)
    return p


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'eval' to the top parser's subcommands."""
    evsub = add_actions(sub, "eval", "evaluate maps, tracks and masks against ground truth", metavar="WHAT")
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
    ins = _against_truth(evsub, "instances", "class-agnostic 3D instance AP and duplicates")
    ins.add_argument("--json", action="store_true")
    ins.set_defaults(func=_cmd_eval_instances)
    rm = _against_truth(evsub, "rooms", "room segmentation (needs MAP_DIR/rooms.npz): precision, recall, F1 and IoU per room")
    rm.add_argument("--iou", type=float, default=0.5, metavar="T", help="IoU at which a predicted room matches a ground-truth room")
    rm.add_argument("--json", action="store_true", help='print {"precision", "recall", "f1", "mean_iou", "type_accuracy", ..., "per_room"}')
    rm.set_defaults(func=_cmd_eval_rooms)
    tr = _against_truth(evsub, "tracking", "2D source-track quality (needs map --save-tracks)", gt="SEQ_DIR")
    tr.add_argument("--json", action="store_true")
    tr.set_defaults(func=_cmd_eval_tracking)

    qe = _against_truth(evsub, "queries", "top-1 hits of the query service's answers (eq. 10) for the ground truth's synonym queries")
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
