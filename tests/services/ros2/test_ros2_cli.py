"""The ROS 2 commands of ``trackgraph`` (services/cli/): ``ros2 bag``, ``synth --rosbag``,
``source --ros2``, ``ros2 play``, the ``deploy/ros2.yaml`` launch plan and the ``ros2`` config
section as ``config check`` reports it. Every failure exits non-zero with one line,
``trackgraph: error: ...``, on stderr (docs/architecture.md, "Command-line contract").

The live commands run against a loopback router in this process (multicast scouting off);
``source --ros2`` and ``ros2 play`` run as subprocesses, so their signal handlers are their own.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.cli import build_parser, main
from shared.config import TransportConfig
from shared.config.ros2 import Ros2LinkConfig
from shared.config.source import RosbagConfig
from shared.datasets import open_sequence
from shared.datasets.rosbag import RosbagReader
from shared.ros2.bagio import bag_source_sequence, bag_topics, read_bag_messages, write_sequence_bag
from shared.runtime.lifeline import STOP_SIGNALS

REPO = Path(__file__).resolve().parents[3]
SYNTHETIC = REPO / "deploy" / "configs" / "synthetic.yaml"
ROS2_LAUNCH = REPO / "deploy" / "ros2.yaml"
N_FRAMES = 12
COLOUR = "/camera/color/image_raw"
DEPTH = "/camera/aligned_depth_to_color/image_raw"
CAMERA_INFO = "/camera/color/camera_info"
SENSOR_TOPICS = {COLOUR: "sensor_msgs/msg/Image", DEPTH: "sensor_msgs/msg/Image", CAMERA_INFO: "sensor_msgs/msg/CameraInfo"}


# -- fixtures ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny synthetic sequence (80x60, 12 frames; about 1.5 s to generate), as
    tests/shared/ros2/test_bagio.py makes it."""
    from shared.synth import generate, preset_config

    out = tmp_path_factory.mktemp("seq") / "tiny"
    cfg = preset_config("small", {"camera": {"width": 80, "height": 60, "frames": N_FRAMES}, "gt": {"point_spacing": 0.1}})
    generate(cfg, 0, out, progress=False)
    return out


@pytest.fixture(scope="module")
def bag(seq: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny sequence as a default bag (Jazzy, MCAP, raw rgb8), for the player."""
    return write_sequence_bag(seq, tmp_path_factory.mktemp("bags") / "tiny_bag").path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _client(endpoint: str, timeout_s: float = 0.5):
    from shared.transport import open_session

    return open_session(TransportConfig(mode="client", connect=[endpoint], connect_timeout_s=timeout_s, shared_memory=False))


@pytest.fixture(scope="module")
def router():
    """A Zenoh router on a free loopback port, in a thread of this process; yields its endpoint."""
    from services.router import run_router

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    stop = threading.Event()
    cfg = TransportConfig(mode="router", connect=[], listen=[endpoint])
    thread = threading.Thread(target=run_router, args=(cfg, stop), daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 20
        while True:
            try:
                _client(endpoint).close()
                break
            except Exception:  # noqa: BLE001 - the router is not up yet
                if time.monotonic() > deadline or not thread.is_alive():
                    raise
                time.sleep(0.1)
        yield endpoint
    finally:
        stop.set()
        thread.join(timeout=10)
        assert not thread.is_alive(), "the router thread did not stop"


@pytest.fixture
def cli(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch):
    """``main(args)`` in-process -> (exit code, stdout, stderr). INFO logs are off (the error
    contract is about the one error line), and the signal handlers and root log handlers a
    command installs are put back, so pytest keeps its own."""
    monkeypatch.setenv("TRACKGRAPH_LOG", "WARNING")

    def call(*args: object) -> tuple[int, str, str]:
        # Drop what came before (another module's in-process calls can leave a root log
        # handler on a closed capture stream, whose "Logging error" reports land here).
        capsys.readouterr()
        handlers = {s: signal.getsignal(s) for s in STOP_SIGNALS}
        root = logging.getLogger()
        log_handlers, level = root.handlers[:], root.level
        try:
            rc = main([str(a) for a in args])
        finally:
            for s, h in handlers.items():
                signal.signal(s, h)
            root.handlers[:] = log_handlers
            root.setLevel(level)
        out, err = capsys.readouterr()
        return rc, out, err

    return call


def _run(*args: object, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """``python -m services.cli ARGS`` as its own process (its own signal handlers)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", "services.cli", *map(str, args)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)  # fmt: skip


def _json_line(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])


def _error_line(err: str) -> str:
    """The one line the command-line contract allows a failure on stderr."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("trackgraph: error: "), err
    return lines[0]


@pytest.fixture
def dead_end(tmp_path: Path) -> list[str]:
    """``--config`` and ``--connect`` for a command that must fail before it connects: a port
    nobody listens on, with a 0.5 s connect timeout, so a regression fails fast instead of
    waiting forever for a router (the default ``connect_timeout_s`` is -1)."""
    cfg = tmp_path / "dead_end.yaml"
    cfg.write_text("transport:\n  connect_timeout_s: 0.5\n  shared_memory: false\n")
    return ["--config", str(cfg), "--connect", f"tcp/127.0.0.1:{_free_port()}"]


# -- ros2 bag ------------------------------------------------------------------------------------


def test_ros2_bag_writes_a_bag_the_reader_maps_and_refuses_to_clobber_it(seq: Path, tmp_path: Path, cli) -> None:
    out = tmp_path / "bags" / "tiny_bag"
    rc, stdout, err = cli("ros2", "bag", seq, "--out", out, "--json")
    assert rc == 0, err
    summary = _json_line(stdout)
    assert set(summary) == {"out", "frames", "seconds", "topics"}
    assert summary["out"] == str(out) and summary["frames"] == N_FRAMES
    assert isinstance(summary["seconds"], float) and summary["seconds"] >= 0
    assert summary["topics"] == {
        "/tf_static": ["tf2_msgs/msg/TFMessage", 1], "/tf": ["tf2_msgs/msg/TFMessage", N_FRAMES + 1],
        CAMERA_INFO: ["sensor_msgs/msg/CameraInfo", N_FRAMES], COLOUR: ["sensor_msgs/msg/Image", N_FRAMES],
        DEPTH: ["sensor_msgs/msg/Image", N_FRAMES],
    }  # fmt: skip
    with open_sequence(seq, "replica") as r:
        want = [r.frame(i) for i in range(len(r))]
    with RosbagReader(out, RosbagConfig()) as r:
        assert len(r) == N_FRAMES
        for i, g in enumerate(want):
            f = r.frame(i)
            np.testing.assert_array_equal(f.rgb, g.rgb)
            np.testing.assert_allclose(f.T_world_cam, g.T_world_cam, rtol=0, atol=1e-9)
    mtime = (out / "metadata.yaml").stat().st_mtime_ns

    rc, stdout, err = cli("ros2", "bag", seq, "--out", out, "--json")
    assert rc == 2 and stdout == ""
    line = _error_line(err)
    assert str(out) in line and "--overwrite" in line
    assert (out / "metadata.yaml").stat().st_mtime_ns == mtime  # untouched

    rc, stdout, err = cli("ros2", "bag", seq, "--out", out, "--overwrite", "--json", "--rate", "15", "--compressed")
    assert rc == 0, err
    summary = _json_line(stdout)
    assert summary["frames"] == N_FRAMES and f"{COLOUR}/compressed" in summary["topics"] and COLOUR not in summary["topics"]
    assert bag_topics(out)[f"{COLOUR}/compressed"] == "sensor_msgs/msg/CompressedImage"
    assert sorted(p.name for p in out.parent.iterdir()) == ["tiny_bag"]  # no temporary folder left


def test_ros2_bag_of_a_missing_sequence_names_it(tmp_path: Path, cli) -> None:
    missing = tmp_path / "no_such_seq"
    rc, stdout, err = cli("ros2", "bag", missing, "--out", tmp_path / "b", "--json")
    assert rc == 2 and stdout == ""
    assert str(missing) in _error_line(err)
    assert not (tmp_path / "b").exists()


def test_ros2_bag_overwrite_deletes_only_a_bag(seq: Path, tmp_path: Path, cli) -> None:
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "notes.txt").write_text("mine")
    rc, _, err = cli("ros2", "bag", seq, "--out", precious, "--overwrite", "--json")
    assert (precious / "notes.txt").is_file() and (precious / "notes.txt").read_text() == "mine"
    assert rc == 2 and "not a ROS 2 bag" in _error_line(err)


def test_ros2_bag_overwrite_that_fails_keeps_the_old_bag(seq: Path, tmp_path: Path, cli) -> None:
    out = tmp_path / "b"
    assert cli("ros2", "bag", seq, "--out", out, "--json")[0] == 0
    rc, _, err = cli("ros2", "bag", tmp_path / "no_such_seq", "--out", out, "--overwrite", "--json")
    assert rc == 2 and "no_such_seq" in _error_line(err)
    assert (out / "metadata.yaml").is_file()


# -- synth --rosbag ------------------------------------------------------------------------------


@pytest.mark.slow
def test_synth_rosbag_names_its_sequence_for_the_simulated_backends(tmp_path: Path, cli) -> None:
    from services.mapping import prepare_config
    from shared.config import load_config

    out = tmp_path / "small"
    rc, stdout, err = cli("synth", "--preset", "small", "--seed", 0, "--out", out, "--rosbag", "small_bag", "--json")
    assert rc == 0, err
    result = _json_line(stdout)
    assert {"frames", "objects", "out", "rosbag"} <= set(result)
    bag_path = Path(result["rosbag"])
    assert bag_path == Path(result["out"]) / "small_bag" and bag_path.parent.resolve() == out.resolve()
    assert (bag_path / "metadata.yaml").is_file()
    assert bag_source_sequence(bag_path) == out.resolve()
    assert sum(m.topic == COLOUR for m in read_bag_messages(bag_path, topics=[COLOUR])) == result["frames"]

    base = load_config(SYNTHETIC)
    assert [v for _, v in base.ground_truth_fields()] == [None, None]  # nothing set before
    cfg = prepare_config(base, bag_path)
    fields = dict(cfg.ground_truth_fields())
    assert set(fields) == {"keyframe_vl.segmenter.ground_truth", "keyframe_vl.vl.ground_truth"}
    assert set(fields.values()) == {str(out.resolve())}


# -- source --------------------------------------------------------------------------------------


def test_source_needs_a_sequence_or_ros2(cli) -> None:
    rc, stdout, err = cli("source")
    assert rc == 2 and stdout == ""
    line = _error_line(err)
    assert "--ros2" in line and "SEQ_DIR" in line


def test_source_ros2_refuses_a_sequence(seq: Path, cli, dead_end: list[str]) -> None:
    rc, stdout, err = cli("source", seq, "--ros2", *dead_end)
    assert rc == 2 and stdout == ""
    assert "drop SEQ_DIR" in _error_line(err)


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--stride", "2"), ("--max-frames", "5"), ("--rate", "10"), ("--dataset", "replica"), ("--mode", "live")],
)
def test_source_ros2_refuses_replay_options(flag: str, value: str, cli, dead_end: list[str]) -> None:
    rc, stdout, err = cli("source", "--ros2", flag, value, *dead_end)
    assert rc == 2 and stdout == ""
    line = _error_line(err)
    assert f"--ros2: {flag} is for replaying a sequence" in line and "ros2.input" in line


def test_source_ros2_bad_domain_names_the_field(cli, dead_end: list[str]) -> None:
    rc, _, err = cli("source", "--ros2", "--domain", "999", *dead_end)
    assert rc == 2
    line = _error_line(err)
    assert "ros2.link.domain_id" in line and "999" in line


@pytest.mark.zenoh
def test_source_ros2_with_nothing_publishing_stops_at_seconds(router: str, tmp_path: Path) -> None:
    """``--seconds 3``: the silent-topic figure needs 2 s of silence from the node's first tick,
    which a 2 s run only just reaches."""
    status = tmp_path / "source.status.json"
    t0 = time.monotonic()
    proc = _run("source", "--ros2", "--seconds", 3, "--json", "--connect", router, "--convention", "bridge", "--domain", 7,
                "--status-file", status, timeout=60)  # fmt: skip
    wall = time.monotonic() - t0
    assert proc.returncode == 0, proc.stderr
    assert 3.0 <= wall < 30, wall
    out = _json_line(proc.stdout)
    assert set(out) == {"published", "dropped", "seconds", "received", "rejected", "error"}
    assert out["published"] == 0 and out["dropped"] == 0 and out["rejected"] == {} and out["error"] is None
    assert 3.0 <= out["seconds"] < 30
    topics = [COLOUR, DEPTH, CAMERA_INFO, "/tf", "/tf_static"]  # the default ros2.input, poses from TF
    assert out["received"] == dict.fromkeys(topics, 0)

    report = json.loads(status.read_text())
    assert report["service"] == "source" and report["state"] == "stopped"
    figures = report["figures"]
    assert sorted(figures["silent_topics"]) == sorted(topics)
    assert figures["convention"] == "bridge"  # the command line's, over the config's default
    assert figures["published"] == 0 and figures["error"] is None
    assert report["published"].get("end_of_sequence") == 1  # fusion may finish its map


# -- ros2 play -----------------------------------------------------------------------------------


@pytest.mark.zenoh
@pytest.mark.parametrize("convention", ["rmw_zenoh", "bridge"])
def test_ros2_play_sends_every_message_of_the_bag(convention: str, router: str, bag: Path) -> None:
    from shared.ros2.link import ZenohRosWire

    messages = list(read_bag_messages(bag))
    want_colour = [m.payload for m in messages if m.topic == COLOUR]
    assert len(want_colour) == N_FRAMES
    lock = threading.Lock()
    got: dict[str, list[tuple[bytes, str | None]]] = {t: [] for t in SENSOR_TOPICS}

    def on_message(topic: str, payload: bytes, ros_type: str | None) -> None:
        with lock:
            got[topic].append((payload, ros_type))

    session = _client(router, timeout_s=5)
    wire = None
    try:
        wire = ZenohRosWire.open(Ros2LinkConfig(convention=convention), session=session)
        # Every sensor topic, not only colour: --wait holds the player until each has a subscriber.
        for topic, ros_type in SENSOR_TOPICS.items():
            wire.subscribe(topic, ros_type, on_message)
        t0 = time.monotonic()
        proc = _run("ros2", "play", bag, "--connect", router, "--json", "--rate", 4, "--convention", convention, "--wait", 10)
        wall = time.monotonic() - t0
        assert proc.returncode == 0, proc.stderr
        assert wall < 8, f"--wait ran to its 10 s limit: the player never saw the subscribers ({wall:.1f} s)"
        stats = _json_line(proc.stdout)
        # The wait ends as soon as everything is in; its limit is generous because a loaded
        # 2-core CI machine (a shuffled full suite) has delivered the last images seconds late.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with lock:
                if all(len(got[t]) >= N_FRAMES for t in SENSOR_TOPICS):
                    break
            time.sleep(0.05)
        time.sleep(0.1)  # nothing beyond the bag arrives late
    finally:
        if wire is not None:
            wire.close()
        session.close()

    assert set(stats) == {"messages", "topics", "seconds", "late_s"}
    assert stats["messages"] == len(messages)
    assert stats["topics"] == {t: sum(m.topic == t for m in messages) for t in bag_topics(bag)}
    assert stats["late_s"] >= 0
    # A quarter of the recorded pace's span (11 frame periods at 30 Hz), and not much more.
    span_s = (messages[-1].time_ns - messages[0].time_ns) * 1e-9
    assert span_s / 4 - 0.01 <= stats["seconds"] < span_s / 4 + 2, (stats, span_s)
    assert [p for p, _ in got[COLOUR]] == want_colour  # every colour image, byte for byte, in order
    assert len(got[DEPTH]) == len(got[CAMERA_INFO]) == N_FRAMES
    # rmw_zenoh keys carry the type; the bridge's do not.
    want_type = "sensor_msgs/msg/Image" if convention == "rmw_zenoh" else None
    assert {t for _, t in got[COLOUR]} == {want_type}


def test_ros2_play_unknown_topic_names_the_available_ones(bag: Path, cli, dead_end: list[str]) -> None:
    rc, stdout, err = cli("ros2", "play", bag, "--topic", "/nope", "--json", *dead_end)
    assert rc == 2 and stdout == ""
    line = _error_line(err)
    assert "'/nope'" in line and str(bag) in line
    for topic in bag_topics(bag):
        assert topic in line


@pytest.mark.parametrize("rate", ["0", "-2"])
def test_ros2_play_refuses_a_rate_that_is_not_positive(rate: str, bag: Path, cli, dead_end: list[str]) -> None:
    rc, stdout, err = cli("ros2", "play", bag, "--rate", rate, "--json", *dead_end)
    assert rc != 0 and stdout == ""
    line = _error_line(err)
    assert "--rate" in line and rate in line


def test_ros2_play_refuses_a_nan_rate(bag: Path, cli, dead_end: list[str]) -> None:
    rc, _, err = cli("ros2", "play", bag, "--rate", "nan", "--json", *dead_end)
    assert rc == 2 and "--rate" in _error_line(err)


def test_ros2_play_of_a_missing_bag_names_it(tmp_path: Path, cli, dead_end: list[str]) -> None:
    missing = tmp_path / "no_bag"
    rc, _, err = cli("ros2", "play", missing, "--json", *dead_end)
    assert rc == 2
    assert f"{missing}: ROS 2 bag not found" in _error_line(err)


# -- deploy/ros2.yaml ----------------------------------------------------------------------------


def test_ros2_launch_plan_runs_a_live_source_and_the_bridge(seq: Path, tmp_path: Path) -> None:
    from services.launch import plan_launch
    from shared.config import load_config

    plan = plan_launch(ROS2_LAUNCH, out=tmp_path / "map", log_dir=tmp_path / "logs")
    parser = build_parser()
    source = plan.commands["source"]
    assert source[:4] == [sys.executable, "-m", "services.cli", "source"]
    args = parser.parse_args(source[3:])
    assert args.ros2 is True and args.sequence is None
    assert args.config == plan.config_path and args.status_file is not None
    bridge = plan.commands["ros2"]
    assert bridge[3:5] == ["serve", "ros2"]
    assert parser.parse_args(bridge[3:]).service == "ros2"
    spec = {s.name: s for s in plan.launch.services}
    assert spec["source"].is_finite is False  # a robot's stream has no end: the launch never "finishes"
    assert not any(s.is_finite for s in plan.launch.services)
    assert plan.sequence is None
    saved = load_config(plan.config_path)
    assert saved.transport.connect == ["tcp/127.0.0.1:7447"] and saved.transport.mode == "client"
    assert saved.ros2.link.convention == "rmw_zenoh" and saved.ros2.input.world_frame == "map"

    # A synthetic sequence lends the simulated backends its ground truth; the live source
    # still takes the robot's topics, not the sequence.
    plan = plan_launch(ROS2_LAUNCH, sequence=seq, out=tmp_path / "map", log_dir=tmp_path / "logs_seq", config=SYNTHETIC)
    assert set(dict(plan.system.ground_truth_fields()).values()) == {str(seq.resolve())}
    assert set(dict(load_config(plan.config_path).ground_truth_fields()).values()) == {str(seq.resolve())}
    source = plan.commands["source"]
    assert str(seq) not in source and str(seq.resolve()) not in source
    assert parser.parse_args(source[3:]).sequence is None and "--ros2" in source


# -- serve ros2, config check --------------------------------------------------------------------


def test_serve_help_lists_ros2(cli, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["serve", "ros2", "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert "ros2" in out.split("\n\n")[0]  # among the services in the usage line
    assert "--status-file" in out and "--connect" in out


@pytest.mark.parametrize(
    ("yaml_text", "names"),
    [
        ("ros2:\n  input:\n    rgb_topc: /x\n", ["ros2.input.rgb_topc", "rgb_topic"]),
        ("ros2:\n  input:\n    rgb_topic: camera/x\n", ["ros2.input.rgb_topic", "camera/x"]),
        ("ros2:\n  input:\n    depth_topic: /camera/color/image_raw\n", ["ros2.input", "rgb_topic", "depth_topic"]),
        ("ros2:\n  link:\n    convention: dds\n", ["ros2.link.convention", "rmw_zenoh", "bridge"]),
        ("ros2:\n  link:\n    domain_id: 300\n", ["ros2.link.domain_id", "300"]),
    ],
    ids=["misspelt_key", "relative_topic", "same_topic_twice", "bad_convention", "domain_out_of_range"],
)
def test_config_check_names_the_bad_ros2_field(yaml_text: str, names: list[str], tmp_path: Path, cli) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml_text)
    rc, stdout, err = cli("config", "check", path)
    assert rc == 2 and stdout == ""
    line = _error_line(err)
    assert str(path) in line
    for name in names:
        assert name in line, (name, line)


def test_config_check_accepts_a_ros2_section(tmp_path: Path, cli) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text("ros2:\n  link:\n    convention: bridge\n    domain_id: 5\n  input:\n    rgb_topic: /cam/rgb\n")
    rc, stdout, err = cli("config", "check", path)
    assert rc == 0, err
    assert stdout.strip() == f"ok: {path}"
