"""The bench's tables as markdown, and its plots as PNG files (matplotlib, no display needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

SEGMENTATION = (("S", "synonyms"), ("D", "depictions"), ("VS", "vis_sim"), ("C", "clutter"), ("M", "missing"), ("I", "incorrect"))
"""OpenLex3D top-5 categories in the paper's column order and names."""


def _f(x: Any, digits: int = 3) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def _hz(x: Any) -> str:
    """Three significant digits: a CPU running the paper's models manages hundredths of a hertz."""
    return "n/a" if x is None else f"{x:.3g}"


def _lag(trial: dict) -> float | None:
    """How far keyframe_vl's answers fell short of the request rate, in % (0 when they kept up)."""
    kf = trial.get("keyframes") or {}
    req, ans = kf.get("request_hz"), kf.get("answer_hz")
    if not req or ans is None:
        return None
    return max(0.0, 100 * (1 - ans / req))


def _gb(mb: Any) -> str:
    return "n/a" if mb is None else f"{mb / 1024:.2f} GB"


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    return [_row(head), _row(["---"] * len(head)), *(_row(r) for r in rows)]


def markdown(res: dict[str, Any]) -> str:
    """Every table of a bench result (see ``services.bench.core.run_bench``)."""
    m = res["machine"]
    lines = [
        f"# TrackGraph bench: {res['sequence_name']}",
        "",
        f"Commit `{res['commit'] or 'unknown'}`, {res['when']}. Machine: {m['cpu'] or 'CPU'} ({m['cpus']} cores)"
        + (f", {m['gpu']}" if m.get("gpu") else ", no GPU")
        + f", {m['platform']}, Python {m['python']}.",
        "",
    ]
    simulated = [c["name"] for c in res["configs"] if "simulated" in (c["backends"].get("segmenter"), c["backends"].get("vl_encoder"))]
    if simulated:
        lines += [
            f"Simulated perception in {', '.join(f'`{n}`' for n in simulated)}: these rows measure the mapping "
            "(tracking, fusion, segments, retrieval) on the synthetic scene's own noisy masks and label "
            "embeddings, not FastSAM or CLIP.",
            "",
        ]
    random = [c["name"] for c in res["configs"] if c.get("random_weights")]
    if random:
        lines += [
            f"Random weights in {', '.join(f'`{n}`' for n in random)}: the real architectures run with untrained "
            "weights (FastSAM takes every detection up to a view's worth of masks), so their times, rates and "
            "memory are the models' own, and their maps, and every quality column of those rows, mean nothing.",
            "",
        ]
    lines += ["Configs and backends (segmenter, VL encoder, dense features):", ""]
    for c in res["configs"]:
        b = c["backends"]
        lines.append(f"- `{c['name']}` ({c['path']}): {b.get('segmenter')}, {b.get('vl_encoder')}, {b.get('dense_features')}")
    lines.append("")

    lines += [_alignment_note(res), "", "## Segmentation (OpenLex3D top-5, share of object points, 3 cm)", ""]
    lines += _table(
        ["config", *(k for k, _ in SEGMENTATION)],
        [[c["name"], *(_f(c["runs"]["3cm"]["eval"][key]) for _, key in SEGMENTATION)] for c in res["configs"]],
    )
    lines += ["", "## Retrieval (OpenLex3D queries, 3 cm)", ""]
    lines += _table(
        ["config", "AP", "AP50", "AP25", "top-1 hit rate"],
        [[c["name"], *(_f(c["runs"]["3cm"]["eval"][k]) for k in ("ap", "ap50", "ap25", "top1_hit_rate"))] for c in res["configs"]],
    )
    lines += ["", "## Efficiency (one process per run)", ""]
    rows = []
    for c in res["configs"]:
        for voxel in ("3cm", "5cm"):
            r = c["runs"].get(voxel)
            if r is None:
                continue
            run = r["run"]
            gpu = "n/a" if run.get("gpu_peak_mb") is None else _gb(run["gpu_peak_mb"])
            rows.append([c["name"], voxel.replace("cm", " cm"), f"{run['frames']}", f"{run['seconds'] / 60:.2f} min", _f(run["hz"], 2), _gb(run["peak_rss_mb"]), gpu])
    lines += _table(["config", "voxel", "frames", "time per sequence", "Hz", "peak RAM", "GPU memory"], rows)
    lines += ["", "## Tracker ablation (3 cm)", ""]
    rows = []
    for c in res["configs"]:
        for mode, key in (("propagation", "3cm"), ("per-frame", "per_frame")):
            r = c["runs"].get(key)
            if r is None:
                continue
            ev, rate = r["eval"], c["rate"].get(key, {})
            rows.append([
                c["name"], mode, _f(ev["ap"]), _f(ev["ap50"]), _f(ev["ap25"]), _f(ev["synonyms"]),
                _f(ev["instances"]["ap50"]), _hz(rate.get("max_sustained_hz")), _hz(r["run"]["hz"]), _gb(r["run"]["peak_rss_mb"]),
            ])  # fmt: skip
    lines += _table(
        ["config", "tracker", "AP", "AP50", "AP25", "S", "class-agnostic AP50", "max input Hz without drops", "in-process Hz", "peak RAM"],
        rows,
    )
    for c in res["configs"]:
        p, f = (c["rate"].get(k, {}).get("max_sustained_hz") for k in ("3cm", "per_frame"))
        if p and f:
            line = f"`{c['name']}`: propagation sustains {p / f:.2f}x the input rate of per-frame segmentation (the paper: 2.5x)."
            seg = c["backends"].get("segmenter")
            if seg in ("simulated", "classical"):
                line += (
                    f" With the `{seg}` segmenter a mask costs little next to FastSAM, so this ratio compares the two"
                    " trackers' own costs, not what propagation saves in segmentation."
                )
            lines += ["", line]
    lines += [
        "",
        "Rate trials (live source, distributed system; frames dropped per stage, keyframe requests dropped by "
        "keyframe_vl, keyframes answered with masks and CLIP features, and the answers' rate against the "
        "requests'):",
        "",
    ]
    rows = []
    for c in res["configs"]:
        for key, mode in (("3cm", "propagation"), ("per_frame", "per-frame")):
            for t in c["rate"].get(key, {}).get("trials", []):
                d, kf = t["drops"], t.get("keyframes") or {}
                rows.append([
                    c["name"], mode, _hz(t["rate_hz"]), str(t["published"]), str(d["source"]), str(d["tracker"]),
                    str(d.get("keyframe_vl")), str(d["fusion"]), str(t.get("frames_in_map")), _hz(t.get("fused_hz")),
                    f"{kf.get('answered')}/{kf.get('requested')}", f"{_hz(kf.get('answer_hz'))} / {_hz(kf.get('request_hz'))}",
                    "yes" if t["sustained"] else "no",
                ])  # fmt: skip
    lines += _table(
        ["config", "tracker", "input Hz", "published", "dropped by source", "by tracker", "requests dropped by keyframe_vl",
         "by fusion", "in map", "fused Hz", "keyframes answered", "answers / requests Hz", "sustained"],
        rows,
    )  # fmt: skip
    lines += ["", "## Gallery ablation (top-1 hit rate of the synonym queries, 3 cm)", ""]
    lines += _table(
        ["config", "max (eq. 10)", "mean"],
        [[c["name"], _f(c["runs"]["3cm"]["eval"]["gallery"]["max"]), _f(c["runs"]["3cm"]["eval"]["gallery"]["mean"])] for c in res["configs"]],
    )
    lines += hierarchy_table(res.get("hierarchy"))
    lines.append("")
    return "\n".join(lines)


def _alignment_note(res: dict[str, Any]) -> str:
    """Which instance alignment the OpenLex3D tables used (the toolbox's default is per_mask
    at 0.001, squared L2); older results did not record it."""
    seen = sorted({
        (ev.get("alignment"), ev.get("alignment_threshold"))
        for c in res["configs"] for r in c["runs"].values() if (ev := r.get("eval")) and ev.get("alignment")
    })  # fmt: skip
    if not seen:
        return "OpenLex3D instance alignment: not recorded."
    return "OpenLex3D instance alignment: " + ", ".join(f"`{a}` at {t:g}" for a, t in seen) + " (the public toolbox's default is `per_mask` at 0.001)."


def hierarchy_table(rows: list[dict[str, Any]] | None) -> list[str]:
    """The rooms of each config's map against the ground-truth rooms (``shared.eval.rooms``),
    with the reason under the table for each row that has none; nothing for a bench result
    from before the table existed."""
    if rows is None:
        return []
    lines = ["", "## Hierarchy (rooms against the ground truth, 3 cm)", ""]
    lines += _table(
        ["config", "rooms predicted / GT", "precision", "recall", "F1 @ 0.5", "over-segmented", "under-segmented", "mean IoU",
         "named right", "type top-1"],
        [[
            r["config"], "n/a" if r.get("n_pred") is None else f"{r['n_pred']} / {r['n_gt']}", _f(r.get("precision")), _f(r.get("recall")),
            _f(r.get("f1")), "n/a" if r.get("over_segmented") is None else str(r["over_segmented"]),
            "n/a" if r.get("under_segmented") is None else str(r["under_segmented"]), _f(r.get("mean_iou")),
            _f(r.get("type_accuracy")), _f(r.get("room_type_top1")),
        ] for r in rows],
    )  # fmt: skip
    lines += [
        "",
        "Ground-truth rooms are their inner floor, predicted rooms `rooms.npz`'s cells, IoU counted in cells and "
        "matched one-to-one at IoU >= 0.5. Over-segmented: ground-truth rooms split among 2 or more predicted rooms "
        "(each with >= 20% of its cells inside); under-segmented: predicted rooms holding >= 20% of 2 or more "
        "ground-truth rooms. Named right: matched rooms whose name is the ground-truth type. Type top-1: for each "
        "room type of the scene, the room whose feature best matches its text is matched to a room of that type.",
    ]
    for r in rows:
        if r.get("error"):
            lines += ["", f"`{r['config']}`: n/a where shown because {r['error']}"]
    return lines


def plots(res: dict[str, Any], folder: Path) -> list[Path]:
    """segmentation.png, retrieval.png, efficiency.png, tracker.png and gallery.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    configs = res["configs"]
    names = [c["name"] for c in configs]
    x = np.arange(len(configs))
    written = []

    def bars(ax, groups: list[tuple[str, list[float]]], width: float) -> None:
        """One bar per config for each (label, values) group, side by side, values printed."""
        for i, (label, vals) in enumerate(groups):
            drawn = ax.bar(x + (i - (len(groups) - 1) / 2) * width, vals, width, label=label)
            ax.bar_label(drawn, fmt="%.2f", fontsize=8)
        ax.set_xticks(x, names)
        ax.legend()

    def save(fig, name: str) -> None:
        path = folder / name
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)

    # Segmentation: one stacked bar per config, categories in the paper's order.
    fig, ax = plt.subplots(figsize=(9, 1.6 + 0.6 * len(configs)))
    colours = ["#2e7d32", "#66bb6a", "#aed581", "#ffb74d", "#bdbdbd", "#e53935"]
    left = np.zeros(len(configs))
    for (label, key), colour in zip(SEGMENTATION, colours, strict=True):
        vals = np.array([100 * (c["runs"]["3cm"]["eval"][key] or 0.0) for c in configs])
        ax.barh(names, vals, left=left, color=colour, label=f"{label} ({key.replace('_', ' ')})")
        for y, (x0, v) in enumerate(zip(left, vals, strict=True)):
            if v >= 6:
                ax.text(x0 + v / 2, y, f"{v:.0f}", ha="center", va="center", fontsize=8)
        left += vals
    ax.set_xlim(0, 100)
    ax.set_xlabel("share of object points (%)")
    ax.set_title("OpenLex3D top-5 segmentation (3 cm)")
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
    save(fig, "segmentation.png")

    # Retrieval: AP, AP50, AP25 per config.
    fig, ax = plt.subplots(figsize=(7, 4))
    bars(ax, [(label, [c["runs"]["3cm"]["eval"][key] or 0.0 for c in configs]) for label, key in (("AP", "ap"), ("AP50", "ap50"), ("AP25", "ap25"))], 0.25)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("average precision")
    ax.set_title("OpenLex3D retrieval (3 cm)")
    save(fig, "retrieval.png")

    # Efficiency: time per sequence and peak RAM, 3 cm against 5 cm.
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 4))
    for a, field, scale, label in ((a1, "seconds", 60, "time per sequence (min)"), (a2, "peak_rss_mb", 1024, "peak RAM (GB)")):
        groups = []
        for voxel in ("3cm", "5cm"):
            runs = [c["runs"].get(voxel) for c in configs]
            groups.append((voxel.replace("cm", " cm"), [r["run"][field] / scale if r else 0.0 for r in runs]))
        bars(a, groups, 0.35)
        a.set_ylabel(label)
    a1.set_title("Mapping time")
    a2.set_title("Peak memory")
    save(fig, "efficiency.png")

    # Tracker ablation: what the map took in and what was dropped, against the input rate.
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    top = 1.0
    for c in configs:
        for key, mode, marker in (("3cm", "propagation", "o"), ("per_frame", "per-frame", "s")):
            info = c["rate"].get(key)
            if not info or not info.get("trials"):
                continue
            trials = sorted(info["trials"], key=lambda t: t["rate_hz"])
            xs = [t["rate_hz"] for t in trials]
            fused = [t.get("fused_hz") or 0.0 for t in trials]
            drops = [100 * (t["dropped"] or 0) / max(t["published"] or 1, 1) for t in trials]
            top = max(top, *xs)
            (line,) = a1.plot(xs, fused, marker=marker, label=f"{c['name']}, {mode}")
            a2.plot(xs, drops, marker=marker, color=line.get_color(), label=f"{c['name']}, {mode}: frames dropped")
            lag = [_lag(t) for t in trials]
            if any(v is not None for v in lag):
                a2.plot(xs, [v or 0.0 for v in lag], marker=marker, color=line.get_color(), linestyle=":", label=f"{c['name']}, {mode}: keyframe_vl behind")
            if info.get("max_sustained_hz"):
                for a in (a1, a2):
                    a.axvline(info["max_sustained_hz"], color=line.get_color(), linestyle="--", linewidth=1)
    a1.plot([0, top], [0, top], color="grey", linewidth=0.8, linestyle=":", label="keeping pace")
    a1.set_xlabel("input rate (Hz)")
    a1.set_ylabel("frames fused per second (Hz)")
    a1.set_title("Map intake (dashed: highest rate sustained)")
    a2.set_xlabel("input rate (Hz)")
    a2.set_ylabel("% (of frames published / of keyframe request rate)")
    a2.set_ylim(bottom=-2)
    a2.set_title("Frames dropped, and how far keyframe answers lag requests")
    a2.legend(fontsize=7)
    a1.legend(fontsize=8)
    save(fig, "tracker.png")

    # Gallery ablation.
    fig, ax = plt.subplots(figsize=(6, 4))
    bars(ax, [(label, [c["runs"]["3cm"]["eval"]["gallery"][g] or 0.0 for c in configs]) for g, label in (("max", "max (eq. 10)"), ("mean", "mean"))], 0.35)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("top-1 hit rate")
    ax.set_title("Gallery scoring (synonym queries, 3 cm)")
    save(fig, "gallery.png")
    return written
