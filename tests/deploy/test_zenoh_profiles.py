"""The Zenoh profiles under deploy/zenoh: every file loads, and on loopback the plain
profile carries data while the secure one demands TLS and a password and enforces its ACL.

Every session uses explicit ``127.0.0.1``/``localhost`` endpoints inserted after loading the
file; the files' own listeners (0.0.0.0, router files only) are always replaced.
"""

from __future__ import annotations

import contextlib
import json
import queue
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

ROOT = Path(__file__).resolve().parents[2]
ZDIR = ROOT / "deploy" / "zenoh"
SECURE = ZDIR / "secure"
MAKE_CERTS = SECURE / "make_certs.py"
CERTS_REL = "deploy/zenoh/secure/certs/"

ALL_FILES = sorted(ZDIR.rglob("*.json5"))
ROUTER_FILES = [ZDIR / "router.json5", SECURE / "router.json5"]
CLIENT_FILES = [p for p in ALL_FILES if p.name != "router.json5"]
SECURE_USERS = {"robot0": "robot.json5", "gpu": "gpu-server.json5", "base": "base-station.json5", "client": "client.json5"}
EXPECTED = [
    "router.json5", "robot.json5", "gpu-server.json5", "base-station.json5",
    "secure/router.json5", "secure/robot.json5", "secure/gpu-server.json5",
    "secure/base-station.json5", "secure/client.json5",
]  # fmt: skip

WAIT = 0.6  # seconds to wait for a sample that must (or must not) arrive on loopback


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def load(path: Path, **overrides) -> zenoh.Config:
    """Load a profile file, then insert ``overrides`` ({"a/b": value}) as JSON5."""
    cfg = zenoh.Config.from_file(str(path))
    for key, value in overrides.items():
        cfg.insert_json5(key, json.dumps(value))
    return cfg


def get_json(cfg: zenoh.Config, key: str):
    return json.loads(cfg.get_json(key))


class Sessions:
    """Opens sessions and closes every one of them, newest first."""

    def __init__(self) -> None:
        self._open: list = []

    def open(self, cfg: zenoh.Config):
        s = zenoh.open(cfg)
        self._open.append(s)
        return s

    def __len__(self) -> int:
        return len(self._open)

    def close(self, keep: int = 0) -> None:
        """Close all but the ``keep`` oldest sessions."""
        while len(self._open) > keep:
            with contextlib.suppress(Exception):
                self._open.pop().close()


@pytest.fixture
def sessions():
    s = Sessions()
    try:
        yield s
    finally:
        s.close()


def subscribe(session, key: str) -> queue.Queue:
    """A subscriber whose callback only queues (key, payload); undeclared with the session."""
    q: queue.Queue = queue.Queue()
    session.declare_subscriber(key, lambda sample: q.put((str(sample.key_expr), sample.payload.to_bytes())))
    return q


def drain(q: queue.Queue, wait: float = WAIT) -> list:
    """Everything that arrives within ``wait`` seconds."""
    out, deadline = [], time.monotonic() + wait
    while (left := deadline - time.monotonic()) > 0:
        try:
            out.append(q.get(timeout=left))
        except queue.Empty:
            break
    return out


def answer_with(session, key: str, text: str):
    """A queryable that answers every query with ``text`` on its own key."""

    def on_query(query) -> None:
        query.reply(key, text.encode())

    return session.declare_queryable(key, on_query)


def ask(session, key: str, timeout: float = 1.0) -> list[str]:
    """Every reply (no consolidation) to one get, sorted; errors as 'ERR:...'."""
    out = []
    for reply in session.get(key, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is not None:
            out.append(reply.ok.payload.to_bytes().decode())
        else:
            out.append("ERR:" + reply.err.payload.to_bytes().decode())
    return sorted(out)


def ask_until(session, key: str, want: list[str], within: float = 3.0) -> list[str]:
    """``ask`` again until the replies are ``want`` (a new queryable takes a moment to
    reach the router) or ``within`` seconds have passed; returns the last replies."""
    deadline = time.monotonic() + within
    while (got := ask(session, key, timeout=0.5)) != want and time.monotonic() < deadline:
        time.sleep(0.05)
    return got


def matched_publisher(session, key: str, within: float = 3.0):
    """A publisher on ``key`` once a subscriber matches it, so what it sends is delivered
    (and anything sent after this point by others reaches the same subscribers)."""
    pub = session.declare_publisher(key)
    deadline = time.monotonic() + within
    while not pub.matching_status.matching:
        assert time.monotonic() < deadline, f"no subscriber matched {key} within {within} s"
        time.sleep(0.02)
    return pub


# --------------------------------------------------------------------------- static checks


def test_expected_files_exist():
    assert sorted(str(p.relative_to(ZDIR)) for p in ALL_FILES) == sorted(EXPECTED)


@pytest.mark.parametrize("path", ALL_FILES, ids=lambda p: str(p.relative_to(ZDIR)))
def test_file_loads_and_is_quiet(path: Path):
    """Loads with zenoh (unknown keys are rejected), no scouting, no stray endpoints."""
    cfg = load(path)
    mode = get_json(cfg, "mode")
    assert mode == ("router" if path.name == "router.json5" else "client")
    assert get_json(cfg, "scouting/multicast/enabled") is False
    assert get_json(cfg, "scouting/gossip/enabled") is False
    assert get_json(cfg, "connect/endpoints") == []
    listen = get_json(cfg, "listen/endpoints")
    if mode == "router":
        assert listen and all(e.endswith(":7447") for e in listen)
    else:
        assert listen == [], "client files never listen"
    assert get_json(cfg, "transport/link/rx/max_message_size") == 256 * 2**20


@pytest.mark.parametrize("path", CLIENT_FILES, ids=lambda p: str(p.relative_to(ZDIR)))
def test_no_wildcard_listener_outside_router_files(path: Path):
    assert "0.0.0.0" not in path.read_text()
    assert "[::]" not in path.read_text()


def test_secure_files_are_tls_only_and_authenticated():
    router = load(SECURE / "router.json5")
    assert get_json(router, "transport/link/protocols") == ["tls"]
    assert all(e.startswith("tls/") for e in get_json(router, "listen/endpoints"))
    tls = get_json(router, "transport/link/tls")
    for key in ("root_ca_certificate", "listen_certificate", "listen_private_key"):
        assert tls[key].startswith(CERTS_REL), key
    assert get_json(router, "transport/auth/usrpwd/dictionary_file").startswith(CERTS_REL)
    acl = get_json(router, "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    for user, name in SECURE_USERS.items():
        cfg = load(SECURE / name)
        assert get_json(cfg, "transport/link/protocols") == ["tls"]
        assert get_json(cfg, "transport/link/tls/root_ca_certificate").startswith(CERTS_REL)
        assert get_json(cfg, "transport/auth/usrpwd/user") == user
        assert get_json(cfg, "transport/auth/usrpwd/password").startswith("NOT-A-SECRET")


def test_credentials_example_matches_the_placeholders():
    lines = [ln for ln in (SECURE / "credentials.example.txt").read_text().splitlines() if ln.strip()]
    pairs = dict(ln.split(":", 1) for ln in lines)
    assert sorted(pairs) == sorted(SECURE_USERS)
    for user, name in SECURE_USERS.items():
        assert pairs[user].startswith("NOT-A-SECRET"), "placeholders must look like placeholders"
        assert get_json(load(SECURE / name), "transport/auth/usrpwd/password") == pairs[user]


def test_acl_is_consistent():
    acl = get_json(load(SECURE / "router.json5"), "access_control")
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    used = set()
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= set(rules), policy
        assert set(policy["subjects"]) <= set(subjects), policy
        used |= set(policy["rules"])
        for rule_id in policy["rules"]:
            # a user's rules are named after it, so a policy cannot pick up another user's rule
            assert any(rule_id.startswith(s + "-") for s in policy["subjects"]), rule_id
    assert used == set(rules), "every rule belongs to a policy"
    users = {u for s in subjects.values() for u in s["usernames"]}
    assert users == set(SECURE_USERS)
    for rule in rules.values():
        assert rule["permission"] == "allow"
        assert all(k.startswith("trackgraph/") for k in rule["key_exprs"]), rule["id"]
        if rule["id"].startswith("robot0-"):
            # a robot's own data stays in its namespace; only "see" rules reach wider
            assert all(k.startswith("trackgraph/robot0/") for k in rule["key_exprs"]) or set(rule["flows"]) == {"egress"}
        if rule["id"].startswith("client-"):
            assert set(rule["messages"]) <= {"query", "reply", "declare_queryable"}
            assert rule["key_exprs"] == ["trackgraph/*/query"]
            if "declare_queryable" in rule["messages"]:
                assert rule["flows"] == ["egress"], "clients may see the query service, never be one"


def test_certs_folder_is_ignored_by_git():
    lines = [ln.strip() for ln in (SECURE / "certs" / ".gitignore").read_text().splitlines()]
    assert "*" in lines and "!.gitignore" in lines
    if shutil.which("git") and (ROOT / ".git").exists():
        for name in ("credentials.txt", "ca-key.pem", "server-key.pem"):
            probe = subprocess.run(["git", "check-ignore", "-q", f"{CERTS_REL}{name}"], cwd=ROOT, capture_output=True)
            assert probe.returncode == 0, f"{CERTS_REL}{name} must be git-ignored"
        probe = subprocess.run(["git", "check-ignore", "-q", f"{CERTS_REL}.gitignore"], cwd=ROOT, capture_output=True)
        assert probe.returncode == 1, "the .gitignore itself is committed"


# --------------------------------------------------------------------------- certificates


def make_certs(out: Path, *args: str) -> dict:
    proc = subprocess.run(
        [sys.executable, str(MAKE_CERTS), str(out), "--json", *args],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_make_certs_writes_a_verifiable_chain(tmp_path: Path):
    files = make_certs(tmp_path / "certs", "--client", "robot0", "--host", "base.example")
    for key in ("ca", "ca_key", "server", "server_key", "client_robot0", "client_robot0_key"):
        assert Path(files[key]).is_file(), key
    assert (Path(files["server_key"]).stat().st_mode & 0o077) == 0, "private keys are not world-readable"
    assert "BEGIN PRIVATE KEY" in Path(files["server_key"]).read_text()
    # refuses to overwrite without --force
    again = subprocess.run([sys.executable, str(MAKE_CERTS), str(tmp_path / "certs")], capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "--force" in again.stderr
    if shutil.which("openssl"):
        ok = subprocess.run(["openssl", "verify", "-CAfile", files["ca"], files["server"], files["client_robot0"]], capture_output=True, text=True)
        assert ok.returncode == 0, ok.stdout + ok.stderr
        text = subprocess.run(["openssl", "x509", "-in", files["server"], "-noout", "-text"], capture_output=True, text=True).stdout
        assert re.search(r"DNS:localhost", text) and "IP Address:127.0.0.1" in text and "DNS:base.example" in text


@pytest.mark.parametrize("backend", ["openssl", "cryptography"])
def test_make_certs_backends(tmp_path: Path, backend: str):
    """Both ways of making certificates give a chain that openssl verifies."""
    if backend == "cryptography":
        pytest.importorskip("cryptography", reason="the cryptography package is not installed")
    if not shutil.which("openssl"):
        pytest.skip("no openssl command to make or verify certificates with")
    files = make_certs(tmp_path, "--backend", backend, "--client", "base")
    assert files["backend"] == backend
    ok = subprocess.run(["openssl", "verify", "-CAfile", files["ca"], files["server"], files["client_base"]], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stdout + ok.stderr


# --------------------------------------------------------------------------- plain profile


@pytest.mark.zenoh
def test_plain_profile_round_trip(sessions: Sessions):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    sessions.open(load(ZDIR / "router.json5", **{"listen/endpoints": [endpoint]}))
    joined = {"connect/endpoints": [endpoint], "connect/timeout_ms": 2000}
    robot = sessions.open(load(ZDIR / "robot.json5", **joined))
    gpu = sessions.open(load(ZDIR / "gpu-server.json5", **joined))
    base = sessions.open(load(ZDIR / "base-station.json5", **joined))
    deltas = subscribe(base, "trackgraph/*/graph/**")
    requests = subscribe(gpu, "trackgraph/robot0/keyframe/request")
    answer_with(gpu, "trackgraph/robot0/vl/embed", "embed")
    matched_publisher(robot, "trackgraph/robot0/graph/delta").put(b"delta")
    matched_publisher(robot, "trackgraph/robot0/keyframe/request").put(b"kf")
    assert drain(deltas) == [("trackgraph/robot0/graph/delta", b"delta")]
    assert drain(requests, 0.2) == [("trackgraph/robot0/keyframe/request", b"kf")]
    assert ask_until(base, "trackgraph/robot0/vl/embed", ["embed"]) == ["embed"]


# --------------------------------------------------------------------------- secure profile


class SecureNet:
    """A router from secure/router.json5 on tls/127.0.0.1:<port>, with its certificate,
    key, CA and credentials file rewritten to a temporary folder."""

    def __init__(self, certs: dict, creds: Path, passwords: dict[str, str]) -> None:
        self.certs, self.creds, self.passwords = certs, creds, passwords
        self.port = free_port()
        self.endpoint = f"tls/127.0.0.1:{self.port}"
        self.sessions = Sessions()

    def router_config(self, **extra) -> zenoh.Config:
        return load(
            SECURE / "router.json5",
            **{
                "listen/endpoints": [self.endpoint],
                "transport/link/tls/root_ca_certificate": self.certs["ca"],
                "transport/link/tls/listen_certificate": self.certs["server"],
                "transport/link/tls/listen_private_key": self.certs["server_key"],
                "transport/auth/usrpwd/dictionary_file": str(self.creds),
                **extra,
            },
        )

    def client_config(self, user: str, password: str | None = None, *, timeout_ms: int = 2000, **extra) -> zenoh.Config:
        return load(
            SECURE / SECURE_USERS[user],
            **{
                "connect/endpoints": [self.endpoint],
                "connect/timeout_ms": timeout_ms,
                "transport/link/tls/root_ca_certificate": self.certs["ca"],
                "transport/auth/usrpwd/password": self.passwords[user] if password is None else password,
                **extra,
            },
        )

    def join(self, user: str):
        return self.sessions.open(self.client_config(user))


@pytest.fixture(scope="module")
def secure_net(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("zenoh-secure")
    certs = make_certs(tmp / "certs", "--client", "robot0")
    passwords = {u: f"test-{u}-{i}-pw" for i, u in enumerate(SECURE_USERS)}
    creds = tmp / "certs" / "credentials.txt"
    creds.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
    net = SecureNet(certs, creds, passwords)
    try:
        net.sessions.open(net.router_config())
        yield net
    finally:
        net.sessions.close()


@pytest.fixture
def net(secure_net: SecureNet):
    """The module's router; the sessions a test opens are closed after it."""
    before = len(secure_net.sessions)
    try:
        yield secure_net
    finally:
        secure_net.sessions.close(keep=before)


@pytest.mark.zenoh
def test_valid_user_over_tls_gets_its_query_answered(net: SecureNet):
    """(a) The base station answers trackgraph/robot0/query; a second base-station session
    and a query-only client both get the answer over TLS with their passwords."""
    server = net.join("base")
    answer_with(server, "trackgraph/robot0/query", "answer")
    asker, client = net.join("base"), net.join("client")
    assert ask_until(asker, "trackgraph/robot0/query", ["answer"]) == ["answer"]
    assert ask(client, "trackgraph/robot0/query") == ["answer"]
    assert ask(client, "trackgraph/*/query") == ["answer"]


@pytest.mark.zenoh
@pytest.mark.parametrize(
    "case",
    ["wrong password", "unknown user", "no credentials", "clear-text tcp", "untrusted CA"],
)
def test_session_is_refused(net: SecureNet, case: str, tmp_path: Path):
    """(b) No session without the right password, over TLS, to the right CA; zenoh.open
    gives up after its connect timeout instead of hanging."""
    cfg = net.client_config("robot0", timeout_ms=500)
    if case == "wrong password":
        cfg = net.client_config("robot0", "not-the-password", timeout_ms=500)
    elif case == "unknown user":
        cfg.insert_json5("transport/auth/usrpwd/user", json.dumps("robot9"))
    elif case == "no credentials":
        cfg = load(
            ZDIR / "robot.json5",  # the plain file: no user, no password
            **{"connect/endpoints": [net.endpoint], "connect/timeout_ms": 500,
               "transport/link/tls/root_ca_certificate": net.certs["ca"]},
        )  # fmt: skip
    elif case == "clear-text tcp":
        cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{net.port}"]))
    elif case == "untrusted CA":
        other = make_certs(tmp_path / "other")
        cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(other["ca"]))
    start = time.monotonic()
    with pytest.raises(zenoh.ZError):
        net.sessions.open(cfg)
    assert time.monotonic() - start < 5.0


@pytest.mark.zenoh
def test_router_refuses_a_clear_text_listener(secure_net: SecureNet):
    cfg = secure_net.router_config(**{"listen/endpoints": [f"tcp/127.0.0.1:{free_port()}"]})
    with pytest.raises(zenoh.ZError):
        zenoh.open(cfg).close()


@pytest.mark.zenoh
def test_only_robots_publish_robot_data(net: SecureNet):
    """(c) A query-only client's put on frames never reaches the robot's subscriber; the
    robot's own put does. Nor may the GPU server or base station publish frames, or a robot
    publish under another robot's namespace."""
    tracker = net.join("robot0")
    frames = subscribe(tracker, "trackgraph/robot0/frames")
    base = net.join("base")
    deltas = subscribe(base, "trackgraph/*/graph/**")
    tracks = subscribe(tracker, "trackgraph/robot0/tracks/**")
    client, gpu, source = net.join("client"), net.join("gpu"), net.join("robot0")
    frames_pub = matched_publisher(source, "trackgraph/robot0/frames")
    deltas_pub = matched_publisher(source, "trackgraph/robot0/graph/delta")
    tracks_pub = matched_publisher(source, "trackgraph/robot0/tracks/frame")
    # both subscribers are known to the router now: the denied puts first, then the robot's
    client.put("trackgraph/robot0/frames", b"from-client")
    gpu.put("trackgraph/robot0/frames", b"from-gpu")
    base.put("trackgraph/robot0/frames", b"from-base")
    client.put("trackgraph/robot0/graph/delta", b"from-client")
    client.put("trackgraph/robot0/tracks/frame", b"from-client")
    gpu.put("trackgraph/robot0/tracks/features", b"from-gpu")
    source.put("trackgraph/robot1/graph/delta", b"other-robot")
    time.sleep(0.2)
    frames_pub.put(b"from-robot")
    deltas_pub.put(b"from-robot")
    tracks_pub.put(b"from-robot")
    assert drain(frames) == [("trackgraph/robot0/frames", b"from-robot")]
    assert drain(deltas, 0.2) == [("trackgraph/robot0/graph/delta", b"from-robot")]
    assert drain(tracks, 0.2) == [("trackgraph/robot0/tracks/frame", b"from-robot")]


@pytest.mark.zenoh
def test_keyframe_and_embed_paths(net: SecureNet):
    """The GPU user gets keyframe requests and answers vl/embed; its masks reach the robot,
    while a robot cannot forge masks and a client cannot pose as vl/embed."""
    gpu = net.join("gpu")
    requests = subscribe(gpu, "trackgraph/robot0/keyframe/request")
    answer_with(gpu, "trackgraph/robot0/vl/embed", "gpu-embed")
    tracker = net.join("robot0")
    masks = subscribe(tracker, "trackgraph/robot0/keyframe/masks")
    answer_with(net.join("client"), "trackgraph/robot0/vl/embed", "client-embed")
    answer_with(net.join("robot0"), "trackgraph/robot0/vl/embed", "robot-embed")
    robot, base, client = net.join("robot0"), net.join("base"), net.join("client")
    matched_publisher(robot, "trackgraph/robot0/keyframe/request").put(b"kf")
    masks_pub = matched_publisher(gpu, "trackgraph/robot0/keyframe/masks")
    robot.put("trackgraph/robot0/keyframe/masks", b"forged")
    time.sleep(0.2)
    masks_pub.put(b"masks")
    assert drain(requests, 0.3) == [("trackgraph/robot0/keyframe/request", b"kf")]
    assert drain(masks) == [("trackgraph/robot0/keyframe/masks", b"masks")]
    assert ask_until(base, "trackgraph/robot0/vl/embed", ["gpu-embed"]) == ["gpu-embed"]
    assert ask_until(robot, "trackgraph/robot0/vl/embed", ["gpu-embed"]) == ["gpu-embed"]
    assert ask(client, "trackgraph/robot0/vl/embed") == []


@pytest.mark.zenoh
def test_snapshots_liveliness_and_matching(net: SecureNet):
    """fusion (robot0) answers graph/snapshot for the base station but not for a client;
    services see each other's liveliness tokens; a robot publisher sees the base station's
    wildcard subscription (matching status, which lossless publishers wait on)."""
    fusion = net.join("robot0")
    answer_with(fusion, "trackgraph/robot0/graph/snapshot", "snapshot")
    gpu, client = net.join("gpu"), net.join("client")
    tokens = [  # a dropped token is undeclared: keep them referenced
        fusion.liveliness().declare_token("trackgraph/robot0/alive/fusion"),
        gpu.liveliness().declare_token("trackgraph/robot0/alive/keyframe_vl"),
        client.liveliness().declare_token("trackgraph/robot0/alive/query"),  # denied
    ]
    base = net.join("base")
    base.declare_subscriber("trackgraph/*/graph/**", lambda _s: None)
    matched_publisher(fusion, "trackgraph/robot0/graph/delta")  # asserts the match
    assert ask_until(base, "trackgraph/robot0/graph/snapshot", ["snapshot"]) == ["snapshot"]
    assert ask(client, "trackgraph/robot0/graph/snapshot") == []
    alive = sorted(str(r.ok.key_expr) for r in base.liveliness().get("trackgraph/*/alive/*", timeout=1.0) if r.ok is not None)
    assert alive == ["trackgraph/robot0/alive/fusion", "trackgraph/robot0/alive/keyframe_vl"]
    assert len(tokens) == 3


@pytest.mark.zenoh
def test_shipped_files_work_through_trackgraph_transport(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The secure files as shipped (relative certs/ paths, placeholder passwords) work
    through shared.transport from a working directory whose certs/ holds make_certs.py's
    output and a copy of credentials.example.txt; a tcp/ connect endpoint is refused."""
    from shared.config import TransportConfig
    from shared.transport import TransportError, open_session

    certs = tmp_path / CERTS_REL
    make_certs(certs)
    shutil.copy(SECURE / "credentials.example.txt", certs / "credentials.txt")
    monkeypatch.chdir(tmp_path)
    port = free_port()
    router = open_session(TransportConfig(
        mode="router", connect=[], listen=[f"tls/127.0.0.1:{port}"], shared_memory=False,
        zenoh_config_file=str(SECURE / "router.json5"),
    ))  # fmt: skip
    opened = [router]
    try:
        for name in ("robot.json5", "base-station.json5"):
            cfg = TransportConfig(
                connect=[f"tls/localhost:{port}"], connect_timeout_s=2.0, shared_memory=False,
                zenoh_config_file=str(SECURE / name),
            )  # fmt: skip
            opened.append(open_session(cfg))
        robot, base = opened[1], opened[2]
        deltas = subscribe(base, "trackgraph/robot0/graph/delta")
        matched_publisher(robot, "trackgraph/robot0/graph/delta").put(b"delta")
        assert drain(deltas) == [("trackgraph/robot0/graph/delta", b"delta")]
        with pytest.raises(TransportError):
            opened.append(open_session(TransportConfig(
                connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_s=0.5,
                zenoh_config_file=str(SECURE / "client.json5"),
            )))  # fmt: skip
    finally:
        for s in reversed(opened):
            s.close()


@pytest.mark.zenoh
def test_optional_mutual_tls(net: SecureNet, sessions: Sessions):
    """With enable_mtls on router and client, a client certificate from make_certs.py
    --client is required on top of the password."""
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    sessions.open(net.router_config(**{"listen/endpoints": [endpoint], "transport/link/tls/enable_mtls": True}))
    mtls = {"connect/endpoints": [endpoint], "transport/link/tls/enable_mtls": True}
    with pytest.raises(zenoh.ZError):
        sessions.open(net.client_config("robot0", timeout_ms=500, **mtls))
    sessions.open(net.client_config(
        "robot0", **mtls,
        **{"transport/link/tls/connect_certificate": net.certs["client_robot0"],
           "transport/link/tls/connect_private_key": net.certs["client_robot0_key"]},
    ))  # fmt: skip
