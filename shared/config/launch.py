"""Launch files (``deploy/*.yaml``): which processes ``trackgraph launch`` starts, how they
connect, and how crashed ones are restarted."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from pydantic import AfterValidator, Field, model_validator

from shared.config.base import StrictModel, load_model


def _launchable(name: str) -> str:
    from shared.registry import SERVICES

    if name != "router" and name not in SERVICES:
        raise ValueError(SERVICES.unknown(name).replace("choose one of: ", "choose one of: router, "))
    return name


ServiceName = Annotated[str, AfterValidator(_launchable)]
"""``router`` or a service of the services registry (shared/registry.py)."""


class RestartPolicy(StrictModel):
    """Bounded restarts: a service that keeps crashing is given up on, and the launch fails."""

    max_restarts: int = Field(3, ge=0)
    """Restarts allowed within ``window_s``; one more crash ends the launch."""
    window_s: float = Field(300.0, gt=0)
    """Sliding window over which restarts are counted (seconds)."""
    backoff_s: float = Field(1.0, ge=0)
    """Wait before the first restart; doubled after each restart in the window."""
    backoff_max_s: float = Field(30.0, ge=0)
    """Longest wait between restarts."""


class ServiceSpec(StrictModel):
    """One process."""

    name: ServiceName
    """What runs: ``router`` is ``trackgraph router``, ``source`` is ``trackgraph source``,
    the others are ``trackgraph serve NAME``."""
    args: list[str] = Field(default_factory=list)
    """Extra command-line arguments (e.g. ``[--resume]`` for fusion)."""
    command: list[str] | None = Field(None, min_length=1)
    """Run this program (an argv list) instead of the built-in service, e.g. a stand-in
    written against docs/wire.md: it takes the service's place (``after``, restarts, and its
    liveliness token ``trackgraph/<robot_id>/alive/<name>``, which it must declare). In each
    item ``{python}`` becomes this Python, ``{here}`` the launch file's folder, ``{connect}``
    the first router endpoint, ``{robot}`` the robot id and ``{config}`` the resolved system
    config. ``args`` are appended."""
    after: list[ServiceName] = Field(default_factory=list)
    """Start once these services are alive (their liveliness tokens are up)."""
    restart: RestartPolicy | None = None
    """Overrides the launch file's policy for this service."""
    finite: bool | None = None
    """It ends by itself when its job is done, and exit 0 then means finished rather than
    crashed. Default: true for ``source`` replaying a recorded sequence (not a live
    ``--ros2`` one) and for ``fusion`` with ``--exit-at-end``."""
    zenoh_config: str | None = None
    """Zenoh JSON5 file for this process (TLS, credentials), relative to the launch file."""

    @property
    def is_finite(self) -> bool:
        if self.finite is not None:
            return self.finite
        return (self.name == "source" and "--ros2" not in self.args) or (self.name == "fusion" and "--exit-at-end" in self.args)


class LaunchConfig(StrictModel):
    """A set of processes that together make (part of) a TrackGraph system."""

    config: str
    """The system config every service gets: a file relative to the launch file
    (``configs/paper.yaml``) or a preset's name (``paper``; shared/presets.py)."""
    set: list[str] = Field(default_factory=list)
    """``KEY=VALUE`` items laid over ``config`` for this launch, as ``--set`` does on the
    command line (e.g. ``[tracker.wait_for_masks=true]``); every key is checked against the
    config, and ``trackgraph launch --set`` items come after these."""
    connect: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    """Router endpoint(s) the services connect to."""
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    """Where a ``router`` service of this launch listens."""
    zenoh_config: str | None = None
    """Zenoh JSON5 file (TLS, credentials) for every service of this launch, relative to the
    launch file; a service's own ``zenoh_config`` takes precedence."""
    sequence: str | None = None
    """Recorded sequence the ``source`` replays (``--sequence`` overrides), relative to the
    current directory."""
    out: str | None = None
    """Map folder of the ``fusion`` service (``--out`` overrides)."""
    log_dir: str | None = None
    """Where each process's output goes (default: ``OUT/logs``, or ``./trackgraph-logs``)."""
    services: list[ServiceSpec]
    """The processes, started in this order (subject to ``after``)."""
    restart: RestartPolicy = Field(default_factory=RestartPolicy)
    """Default restart policy."""
    alive_timeout_s: float = Field(120.0, gt=0)
    """How long a started service may take to announce itself before it counts as failed
    (model loading on a cold machine takes a while). It does not run while the service's own
    status reports say ``starting``: it is up and waits for what it needs (the query service
    for a ``vl/embed`` on a machine started later)."""
    unresponsive_s: float = Field(15.0, gt=0)
    """A running service whose liveliness token has been gone this long (frozen, or cut off
    from the router past the link lease) is restarted under its policy."""
    stop_timeout_s: float = Field(30.0, gt=0)
    """Grace between SIGTERM and SIGKILL at shutdown (fusion writes its last snapshot)."""
    exit_when_finished: bool = True
    """When every finite service has finished, stop the others and exit 0 (a replayed
    sequence). False keeps the system up until Ctrl-C."""

    @model_validator(mode="before")
    @classmethod
    def _no_overrides(cls, data: Any) -> Any:
        if isinstance(data, dict) and "overrides" in data:
            raise ValueError("'overrides' is replaced by 'set': a list of KEY=VALUE items, e.g. set: [tracker.wait_for_masks=true]")
        return data

    @model_validator(mode="after")
    def _consistent(self) -> LaunchConfig:
        names = [s.name for s in self.services]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"services listed twice: {', '.join(sorted(dup))}")
        for s in self.services:
            missing = [a for a in s.after if a not in names]
            if missing:
                raise ValueError(f"{s.name}.after names services not in this launch: {', '.join(missing)}")
            if s.name == "router" and s.after:
                raise ValueError("the router starts first; it cannot wait for other services")
        return self


def load_launch(path: str | Path) -> LaunchConfig:
    """A launch file; errors name the file and the bad key."""
    return load_model(LaunchConfig, path)
