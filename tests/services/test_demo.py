"""``trackgraph demo`` (what ``make demo`` runs) on the ``small`` preset: every service as a
process, queries through the live service, and every promised file in the output folder."""

from __future__ import annotations

import json

import pytest
from PIL import Image

from services.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]


@pytest.mark.timeout(900)
def test_demo_writes_the_report_pictures_and_recordings(tmp_path, capsys):
    out = tmp_path / "demo_out"
    assert main(["demo", "--preset", "small", "--out", str(out), "--json"]) == 0
    r = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert "simulated" in r["perception"] and r["frames"] == 120
    assert all(s["restarts"] == 0 for s in r["services"].values()), r["services"]
    assert r["services"]["source"]["state"] == r["services"]["fusion"]["state"] == "finished"
    assert all(s["peak_rss_mb"] > 0 for s in r["services"].values())
    # Six text queries and one image query, each answered by the live service.
    kinds = [q["kind"] for q in r["queries"]]
    assert kinds.count("text") == 6 and kinds.count("image") == 1
    assert all(q["hits"] for q in r["queries"])
    hit = sum(q["hits"][0]["iou"] >= 0.25 for q in r["queries"])
    assert hit >= 4, r["queries"]
    assert r["metrics"]["top1_synonym_queries_over_20cm"] is not None
    for name in ("report.md", "report.json", "map.rrd", "map/live.rrd", "map/run.json", "map/config.yaml", "pictures/map.png", "pictures/queries.png", "queries/image_query.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert len(list((out / "pictures").glob("query_*.png"))) == 7
    report = (out / "report.md").read_text()
    for words in ("Perception", "peak RSS", "latency", "instance AP50", "rerun"):
        assert words in report
    with Image.open(out / "pictures" / "map.png") as im:
        assert im.size[0] > 1000 and len(set(im.convert("RGB").getdata())) > 50

    # The saved map answers offline queries and renders, through the command line.
    capsys.readouterr()
    assert main(["query", str(out / "map"), "chair", "--top-k", "2", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 2 and {"segment", "score", "centroid", "bbox"} <= set(rows[0])
    assert rows[0]["score"] >= rows[1]["score"]
    assert main(["query", str(out / "map"), "chair", "--room", "999"]) == 2
    assert "unknown room 999" in capsys.readouterr().err
    assert main(["query", str(tmp_path / "nowhere"), "chair"]) == 2
    assert main(["view", str(out / "map"), "--query", "chair", "--png", str(tmp_path / "png"), "--out", str(tmp_path / "v.rrd")]) == 0
    assert (tmp_path / "v.rrd").stat().st_size > 10_000 and (tmp_path / "png" / "query_0.png").is_file()
