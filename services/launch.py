"""``trackgraph launch FILE``: every service of a launch file as its own OS process.

The launcher starts the router first, then the services in file order (each waiting for the
services it names in ``after`` to be alive), and watches them two ways: the process itself
(an exit is a crash unless a finite service finished with status 0) and its liveliness token
(``trackgraph/<robot>/alive/<service>``, which vanishes within the link lease when a process
freezes or loses the router). What each service is doing comes from its own reports
(``ServiceStatus`` on ``trackgraph/<robot>/status/<service>``, once a second): the status
table shows each one's rate, drops, queue depth and progress (frames done of total, ETA). A crashed or unresponsive service is restarted under its
bounded policy, with exponential backoff; fusion is restarted with ``--resume`` so it goes on
from its last snapshot. A service that exhausts its policy ends the launch with an error.
On Ctrl-C (SIGINT, SIGTERM or SIGHUP), or when every finite service has finished, the others
get SIGTERM in reverse start order (the router last), and SIGKILL after ``stop_timeout_s``.
A launcher that dies without that (SIGKILL, a crash) still takes its services with it: each
one holds a lifeline to it (:mod:`shared.runtime.lifeline`).

Each child runs ``python -m services.cli ...`` in a new process group with its output in
``LOG_DIR/<service>.log`` and its last status report, written at stop, in
``LOG_DIR/<service>.status.json``; the resolved system config they all read is
``LOG_DIR/config.yaml``.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from shared.config.base import ConfigError, save_resolved, validate
from shared.config.launch import LaunchConfig, RestartPolicy, ServiceSpec, load_launch
from shared.config.root import TrackGraphConfig
from shared.procfs import status_mb
from shared.runtime.lifeline import LAUNCHER_GRACE_ENV, LAUNCHER_PID_ENV, install_stop_handlers
from shared.runtime.status import read_status, status_path

if TYPE_CHECKING:
    from shared.messages.status import ServiceStatus

log = logging.getLogger(__name__)

TICK_S = 0.2
REPORT_GONE_S = 3.0
"""A liveliness token gone this long makes a service show as unresponsive."""


class LaunchError(RuntimeError):
    """The launch could not start, or a service failed beyond its restart policy."""


@dataclass
class Plan:
    """A launch file resolved against the file system: configs written, commands built."""

    launch: LaunchConfig
    source: Path
    log_dir: Path
    config_path: Path
    system: TrackGraphConfig
    sequence: Path | None
    out: Path | None
    commands: dict[str, list[str]] = field(default_factory=dict)


def plan_launch(
    path: Path | str,
    *,
    sequence: Path | None = None,
    out: Path | None = None,
    log_dir: Path | None = None,
    config: Path | str | None = None,
    sets: Sequence[str] = (),
) -> Plan:
    """Read ``path`` (a launch file, or its name: ``local``), write the resolved system config,
    and build every command line; ``config`` (a file or a preset's name) replaces the file's
    system config, and ``sets`` (``KEY=VALUE``) come after the file's own ``set`` items."""
    from services.mapping import prepare_config
    from shared.config import load_config
    from shared.presets import launch_path

    path = launch_path(path)
    launch = load_launch(path)
    here = path.parent

    def rel(p: str) -> Path:
        q = Path(p)
        return q if q.is_absolute() else here / q

    sequence = sequence or (Path(launch.sequence) if launch.sequence else None)
    out = out or (Path(launch.out) if launch.out else None)
    names = {s.name for s in launch.services}
    live = any(s.name == "source" and "--ros2" in s.args for s in launch.services)
    if "source" in names and sequence is None and not live:
        raise ConfigError(f"{path}: the source needs a sequence: set 'sequence' or pass --sequence SEQ_DIR")
    if sequence is not None and not Path(sequence).is_dir():
        raise ConfigError(f"{sequence}: no such sequence folder")
    if "fusion" in names and out is None:
        raise ConfigError(f"{path}: fusion needs a map folder: set 'out' or pass --out MAP_DIR")
    log_dir = Path(log_dir or (launch.log_dir and Path(launch.log_dir)) or (out / "logs" if out else Path("trackgraph-logs")))
    log_dir.mkdir(parents=True, exist_ok=True)

    for zc in [launch.zenoh_config] + [s.zenoh_config for s in launch.services]:
        if zc is not None and not rel(zc).is_file():
            raise ConfigError(f"{path}: zenoh config {rel(zc)} does not exist")
    if config is None:
        config = rel(launch.config) if rel(launch.config).is_file() else launch.config
    try:
        base = load_config(config, [*launch.set, *sets])
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    data = base.model_dump(mode="json")
    data["transport"] = {**data["transport"], "mode": "client", "connect": list(launch.connect), "listen": []}
    if launch.zenoh_config is not None:
        data["transport"]["zenoh_config_file"] = str(rel(launch.zenoh_config))
    system = validate(TrackGraphConfig, data, f"{path}: transport")
    if sequence is not None:
        system = prepare_config(system, Path(sequence))
    config_path = save_resolved(system, log_dir / "config.yaml")
    for spec in launch.services:
        # A report an earlier launch left in this folder must not pass for this one's.
        status_path(log_dir, spec.name).unlink(missing_ok=True)
    plan = Plan(launch, path, log_dir, config_path, system, Path(sequence) if sequence else None, Path(out) if out else None)

    py = [sys.executable, "-m", "services.cli"]
    for spec in launch.services:
        cfg_file = config_path
        if spec.zenoh_config is not None and spec.name != "router":
            own = system.model_copy(update={"transport": system.transport.model_copy(update={"zenoh_config_file": str(rel(spec.zenoh_config))})})
            cfg_file = save_resolved(own, log_dir / f"config-{spec.name}.yaml")
        if spec.command is not None:
            fill = {"{python}": sys.executable, "{here}": str(here.resolve()), "{connect}": launch.connect[0],
                    "{robot}": system.robot_id, "{config}": str(cfg_file)}  # fmt: skip
            cmd = list(spec.command)
            for token, value in fill.items():
                cmd = [arg.replace(token, value) for arg in cmd]
        elif spec.name == "router":
            cmd = [*py, "router", *sum((["--listen", ep] for ep in launch.listen), [])]
            if spec.zenoh_config is not None:
                cmd += ["--zenoh-config", str(rel(spec.zenoh_config))]
        elif spec.name == "source":
            # A live source takes the robot's topics; a sequence given with it only lends its
            # ground truth to simulated backends (prepare_config above).
            seq_arg = [] if "--ros2" in spec.args else [str(sequence)]
            cmd = [*py, "source", *seq_arg, "--config", str(cfg_file), "--status-file", str(status_path(log_dir, spec.name))]
        else:
            cmd = [*py, "serve", spec.name, "--config", str(cfg_file), "--status-file", str(status_path(log_dir, spec.name))]
            if spec.name == "fusion":
                cmd += ["--out", str(out)]
            if spec.name == "viewer":
                cmd += ["--out", str((out or log_dir) / "live.rrd")]
        plan.commands[spec.name] = cmd + list(spec.args)
    return plan


@dataclass
class Proc:
    """One supervised service."""

    spec: ServiceSpec
    policy: RestartPolicy
    cmd: list[str]
    log_path: Path
    state: str = "pending"
    """pending, starting, alive, unresponsive, backoff, finished, failed, stopped."""
    popen: subprocess.Popen | None = None
    started_at: float = 0.0
    gone_since: float | None = None
    """When its liveliness token was last seen going away while running."""
    restarts: list[float] = field(default_factory=list)
    next_start: float = 0.0
    exit_codes: list[int] = field(default_factory=list)
    reason: str = ""
    peak_rss_mb: float = 0.0
    """Largest resident memory seen of any run of the process (Linux /proc)."""
    starting_seen: float = 0.0
    """When this run last reported state ``starting`` (waiting for what it needs to be alive)."""

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def pid(self) -> int | None:
        return self.popen.pid if self.popen is not None and self.popen.poll() is None else None


class Supervisor:
    """Starts, watches, restarts and stops the processes of one :class:`Plan`."""

    def __init__(self, plan: Plan, *, status: bool = True) -> None:
        self.plan = plan
        self.launch = plan.launch
        self.topics_root = f"trackgraph/{plan.system.robot_id}/alive"
        self.procs = {
            s.name: Proc(s, s.restart or self.launch.restart, plan.commands[s.name], plan.log_dir / f"{s.name}.log")
            for s in self.launch.services
        }
        self.order = [s.name for s in self.launch.services]
        self.stop_event = threading.Event()
        self.session = None
        self.watcher = None
        self.bus = None
        self.reports = None
        """The services' ServiceStatus reports (a :class:`services.monitor.StatusWatch`), once connected."""
        self._connecting: threading.Thread | None = None
        self._watching_since = 0.0
        self._status = status
        self._events: list[str] = []
        self.error: str | None = None

    # ------------------------------------------------------------------ helpers

    def _alive(self, name: str) -> bool:
        p = self.procs[name]
        if name == "router":
            return p.popen is not None and p.popen.poll() is None and _port_open(self.launch.listen)
        return self.watcher is not None and f"{self.topics_root}/{name}" in self.watcher.alive()

    def _reports_starting(self, p: Proc) -> bool:
        """This run of ``p`` (its pid) reports state ``starting`` now: it is up but waits for
        what it needs to do its job (keyframe_vl loading its models, the query service for a
        ``vl/embed`` that may be on a machine not started yet), so its alive time-out waits too."""
        got = None if self.reports is None or p.popen is None else self.reports.get(p.name)
        if got is None:
            return False
        st, age = got
        return st.pid == p.popen.pid and st.state == "starting" and age < REPORT_GONE_S

    def _event(self, msg: str) -> None:
        log.info("%s", msg)
        self._events = (self._events + [f"{time.strftime('%H:%M:%S')} {msg}"])[-6:]

    def _spawn(self, p: Proc) -> None:
        cmd = list(p.cmd)
        if p.name == "fusion" and p.exit_codes and "--resume" not in cmd:
            cmd.append("--resume")  # a crashed fusion goes on from its last snapshot
        # The lifeline (shared/runtime/lifeline.py): the service ends with this launcher even
        # when it dies without stopping them (SIGKILL, OOM killer), within its own grace.
        env = {**os.environ, "PYTHONUNBUFFERED": "1", LAUNCHER_PID_ENV: str(os.getpid()), LAUNCHER_GRACE_ENV: f"{self.launch.stop_timeout_s:g}"}
        logf = open(p.log_path, "ab")  # noqa: SIM115 - the child owns it for its lifetime
        try:
            logf.write(f"\n==== {time.strftime('%Y-%m-%d %H:%M:%S')} start: {' '.join(cmd)}\n".encode())
            logf.flush()
            p.popen = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, start_new_session=True)
        finally:
            logf.close()
        p.state, p.started_at, p.gone_since = "starting", time.monotonic(), None
        self._event(f"{p.name} started (pid {p.popen.pid})")

    def _crashed(self, p: Proc, why: str) -> None:
        now = time.monotonic()
        if p.popen is not None and p.popen.poll() is None:
            _kill(p.popen, signal.SIGKILL, 5.0)
        recent = [t for t in p.restarts if now - t <= p.policy.window_s]
        if len(recent) >= p.policy.max_restarts:
            p.state, p.reason = "failed", why
            self._event(f"{p.name} failed: {why}; {len(recent)} restarts in {p.policy.window_s:.0f} s, giving up")
            self.error = f"{p.name} failed: {why} (log: {p.log_path})"
            return
        delay = min(p.policy.backoff_s * 2 ** len(recent), p.policy.backoff_max_s)
        p.restarts = recent + [now]
        p.state, p.next_start, p.reason = "backoff", now + delay, why
        self._event(f"{p.name} {why}; restarting in {delay:.1f} s ({len(p.restarts)}/{p.policy.max_restarts})")

    def _ready_to_start(self, p: Proc) -> bool:
        if "router" in self.procs and p.name != "router" and not self._alive("router"):
            return False
        return all(self.procs[d].state in ("alive", "finished") for d in p.spec.after)

    def _open_session(self) -> None:
        """Join the network in the background: a robot's launch may come up before the base
        station's router, and its services must start anyway (they wait for it themselves)."""
        from services.monitor import StatusWatch
        from shared.transport import LivelinessWatcher, ZenohBus, open_session

        def connect() -> None:
            transport = self.plan.system.transport.model_copy(update={"connect_timeout_s": -1.0})
            session = open_session(transport)
            if self.stop_event.is_set():
                session.close()
                return
            self.session = session
            self._watching_since = time.monotonic()
            self.bus = ZenohBus(session, self.plan.system.robot_id, transport.codec)
            self.reports = StatusWatch(self.bus, self.plan.system.robot_id)
            self.watcher = LivelinessWatcher(session, f"{self.topics_root}/**")
            self._event("watching liveliness and status reports on " + ", ".join(transport.connect))

        self._connecting = threading.Thread(target=connect, name="launch:session", daemon=True)
        self._connecting.start()

    # ------------------------------------------------------------------ the loop

    def step(self) -> None:
        """One supervision tick."""
        now = time.monotonic()
        if self._connecting is None and ("router" not in self.procs or self._alive("router")):
            self._open_session()
        for name in self.order:
            p = self.procs[name]
            if p.state == "pending" and self._ready_to_start(p):
                self._spawn(p)
            elif p.state == "backoff" and now >= p.next_start and self._ready_to_start(p):
                self._spawn(p)
            if p.popen is None or p.state in ("finished", "failed", "stopped", "backoff"):
                continue
            code = p.popen.poll()
            if code is not None:
                p.exit_codes.append(code)
                if code == 0 and p.spec.is_finite:
                    p.state = "finished"
                    self._event(f"{p.name} finished")
                else:
                    self._crashed(p, f"exited with status {code}" if code >= 0 else f"killed by {signal.Signals(-code).name}")
                continue
            p.peak_rss_mb = max(p.peak_rss_mb, _peak_rss_mb(p.popen.pid))
            if self._alive(name):
                if p.state != "alive":
                    self._event(f"{p.name} alive" + (" again" if p.state == "unresponsive" else ""))
                p.state, p.gone_since = "alive", None
            elif self.watcher is None and name != "router":
                continue  # not connected yet: liveliness cannot be told
            elif p.state == "starting" and self._reports_starting(p):
                p.starting_seen = now  # up and saying why it is not alive yet: no time-out runs
            elif p.state == "starting" and now - max(p.started_at, self._watching_since, p.starting_seen) > self.launch.alive_timeout_s:
                self._crashed(p, f"not alive {self.launch.alive_timeout_s:.0f} s after start")
            elif p.state in ("alive", "unresponsive") and name != "router":
                p.gone_since = p.gone_since or now
                # A token can blink while a link re-forms; only a lasting absence is news. A
                # finite service drops its token as it shuts down, and may take a few seconds to
                # exit after that (a large heap to free): only the restart threshold tells.
                report_after = self.launch.unresponsive_s if p.spec.is_finite else min(REPORT_GONE_S, self.launch.unresponsive_s)
                if p.state == "alive" and now - p.gone_since > report_after:
                    p.state = "unresponsive"
                    self._event(f"{p.name} unresponsive (liveliness token gone)")
                if now - p.gone_since > self.launch.unresponsive_s:
                    self._crashed(p, f"unresponsive for {now - p.gone_since:.0f} s")

    def finished(self) -> bool:
        finite = [p for p in self.procs.values() if p.spec.is_finite]
        return bool(finite) and all(p.state == "finished" for p in finite)

    def run(self) -> dict[str, Any]:
        """Supervise until Ctrl-C, a failure, or (``exit_when_finished``) the job's end."""
        live = _StatusView(self) if self._status else None
        try:
            while not self.stop_event.is_set():
                self.step()
                if live is not None:
                    live.update()
                if self.error is not None:
                    break
                if self.launch.exit_when_finished and self.finished():
                    self._event("every finite service finished")
                    break
                self.stop_event.wait(TICK_S)
        finally:
            self.shutdown()
            if live is not None:
                live.close()
        if self.error is not None:
            raise LaunchError(self.error)
        return self.summary()

    def shutdown(self) -> None:
        """SIGTERM in reverse start order (router last), SIGKILL after the grace."""
        running = [self.procs[n] for n in reversed(self.order) if self.procs[n].pid is not None]
        routers = [p for p in running if p.name == "router"]
        for p in [p for p in running if p.name != "router"] + routers:
            if p.name == "router":
                # Our own session goes while its router is still there: closing a client
                # session whose router has gone has aborted the launcher at exit.
                self._close_session()
            _kill(p.popen, signal.SIGTERM, self.launch.stop_timeout_s)
            if p.state not in ("finished", "failed"):
                p.state = "stopped"
            self._event(f"{p.name} stopped")
        self._close_session()

    def report(self, name: str):
        """(newest ServiceStatus of ``name``, its age in seconds), or None before its first."""
        return None if self.reports is None else self.reports.get(name)

    def final_report(self, name: str):
        """What ``name`` last reported: its live report while it runs; once it has exited, the
        ``status.json`` it wrote at stop (if any), else its last live report."""
        p = self.procs[name]
        live = self.report(name)
        if p.pid is None:
            path = status_path(self.plan.log_dir, name)
            if path.is_file():
                try:
                    return read_status(path)
                except ValueError as exc:
                    log.warning("%s", exc)
        return None if live is None else live[0]

    def _close_session(self) -> None:
        if self.reports is not None:
            self.reports.close()
            self.reports = None
        if self.bus is not None:
            self.bus.close()  # its endpoints; the session is closed below
            self.bus = None
        if self.watcher is not None:
            self.watcher.close()
            self.watcher = None
        if self.session is not None:
            self.session.close()
            self.session = None

    def summary(self) -> dict[str, Any]:
        from services.monitor import report_summary

        def status(name: str) -> dict[str, Any] | None:
            if name == "router":
                return None
            st = self.final_report(name)
            return None if st is None else report_summary(st)

        return {
            "services": {
                p.name: {
                    "state": p.state,
                    "restarts": len(p.restarts),
                    "exit_codes": p.exit_codes,
                    "peak_rss_mb": round(p.peak_rss_mb, 1),
                    "log": str(p.log_path),
                    "status": status(p.name),
                    "status_file": None if p.name == "router" else str(status_path(self.plan.log_dir, p.name)),
                }
                for p in self.procs.values()
            },
            "log_dir": str(self.plan.log_dir),
            "config": str(self.plan.config_path),
            "out": None if self.plan.out is None else str(self.plan.out),
        }


class _StatusView:
    """One status table, redrawn in place on a terminal, or state changes as log lines."""

    def __init__(self, sup: Supervisor) -> None:
        from rich.console import Console

        self.sup = sup
        self.console = Console(stderr=True)
        self.live = None
        if self.console.is_terminal:
            from rich.live import Live

            self.live = Live(self.table(), console=self.console, refresh_per_second=4, transient=False)
            self.live.start()
            # Log lines written past the live table leave pieces of it behind on the screen;
            # through Live's own stderr proxy they print above the table instead.
            self._moved = [h for h in logging.getLogger().handlers if type(h) is logging.StreamHandler and h.stream is sys.__stderr__]
            for h in self._moved:
                h.setStream(sys.stderr)

    def table(self):
        return launch_table(self.sup)

    def update(self) -> None:
        if self.live is not None:
            self.live.update(self.table())

    def close(self) -> None:
        if self.live is not None:
            self.live.update(self.table())
            self.live.stop()
            for h in self._moved:
                h.setStream(sys.__stderr__)


LAUNCH_COLUMNS = ("service", "state", "pid", "up", "restarts", "Hz", "drops", "queue", "progress", "log")


def launch_table(sup: Supervisor, now: float | None = None):
    """The launcher's table: each process's state (from the supervisor) and what its own
    reports say (rate, drops, queue depth, frames done of total with an ETA)."""
    from rich.table import Table

    from services.monitor import STALE_S, report_cells, with_source_total

    now = time.monotonic() if now is None else now
    t = Table(title=f"trackgraph launch {sup.plan.source}", header_style="bold", caption="\n".join(sup._events))
    for col in LAUNCH_COLUMNS:
        t.add_column(col, justify="right" if col in ("pid", "restarts", "Hz", "drops", "queue") else "left")
    colours = {"alive": "green", "finished": "cyan", "failed": "red", "unresponsive": "yellow", "backoff": "yellow"}

    def latest(name: str) -> tuple[ServiceStatus, float] | None:
        p = sup.procs[name]
        if name == "router":
            return None
        if p.pid is not None:
            return sup.report(name)
        st = sup.final_report(name)  # it has exited: what it reported last
        return None if st is None else (st, 0.0)

    source = latest("source") if "source" in sup.procs else None
    for name in sup.order:
        p = sup.procs[name]
        up = f"{now - p.started_at:.0f} s" if p.pid is not None else "-"
        got = latest(name)
        cells = report_cells(None if got is None else with_source_total(got[0], None if source is None else source[0]))
        stale = got is not None and got[1] > STALE_S
        figures = [f"[dim]{cells[c]}[/]" if stale else cells[c] for c in ("Hz", "drops", "queue", "progress")]
        t.add_row(name, f"[{colours.get(p.state, 'white')}]{p.state}[/]", str(p.pid or "-"), up, str(len(p.restarts)), *figures, str(p.log_path))
    return t


def _peak_rss_mb(pid: int) -> float:
    """The process's high-water resident memory (VmHWM), 0 where /proc cannot tell."""
    return status_mb("VmHWM", pid) or 0.0


def _port_open(endpoints: list[str]) -> bool:
    for ep in endpoints:
        proto, _, rest = ep.partition("/")
        if proto not in ("tcp", "tls"):
            return True  # no cheap probe for other links: trust the process
        host, _, port = rest.rpartition(":")
        host = "127.0.0.1" if host in ("0.0.0.0", "", "[::]") else host.strip("[]")
        try:
            with socket.create_connection((host, int(port.split("#")[0])), timeout=0.2):
                return True
        except OSError:
            continue
    return False


def _kill(popen: subprocess.Popen, sig: int, timeout: float) -> None:
    """Signal the child's process group and wait; SIGKILL it if it outlives ``timeout``."""
    if popen.poll() is not None:
        return
    try:
        os.killpg(popen.pid, sig)
    except ProcessLookupError:
        return
    try:
        popen.wait(timeout)
    except subprocess.TimeoutExpired:
        log.warning("pid %d ignored %s for %.0f s: killing it", popen.pid, signal.Signals(sig).name, timeout)
        try:
            os.killpg(popen.pid, signal.SIGKILL)
        except ProcessLookupError:
            return
        popen.wait(10)


def run_launch(
    path: Path | str,
    *,
    sequence: Path | None = None,
    out: Path | None = None,
    log_dir: Path | None = None,
    status: bool = True,
    sets: Sequence[str] = (),
) -> dict[str, Any]:
    """Plan and supervise a launch file until it ends; SIGINT/SIGTERM/SIGHUP stop it cleanly."""
    plan = plan_launch(path, sequence=sequence, out=out, log_dir=log_dir, sets=sets)
    sup = Supervisor(plan, status=status)
    install_stop_handlers(sup.stop_event.set)  # SIGHUP too: a closed terminal stops the launch in order
    return sup.run()
