"""Launch files: which nodes of a run start on which host (`LaunchFile`, loaded by `load`).

A launch file (YAML, validated by `LaunchFile`, unknown keys are errors) names the run, its
profile, the Zenoh topology and, per host, the nodes to start with their counts and restart
policy::

    run: exp1
    run_dir: runs/exp1             # or a study: `study: studies/s1` and `study_runs: [...]`
    profile: demo                  # a built-in profile or a profile YAML file
    seed: 1                        # optional: the evolution seed (one per replicate)
    topology: {kind: peer_mesh, seed: "tcp/10.0.0.5:7447"}     # or {kind: router, endpoint, host}
    certs: certs                   # optional: per-node TLS identities (`derl certs FILE`)
    hosts:
      - name: head
        listen: "tcp/10.0.0.5:7447"
        nodes: [{role: coordinator}]
      - name: gpu1
        address: gpu1.example.org
        ssh: true                  # or "user@gpu1.example.org"
        listen: "tcp/10.0.0.6:7447"
        nodes: [{role: trainer, count: 8, restart: on-failure, max_restarts: 5}]

`nodes.launch.commands` turns it into command lines, `nodes.launch.supervisor` runs them.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from derl.messages.types import Id
from derl.nodes.runtime.bus import LOOPBACK_ANY_PORT

ROLES = ("router", "coordinator", "trainer", "evaluator")  # also the start order on a host
LOCAL_ADDRESSES = {"localhost", "local", "127.0.0.1", "::1"}
WILDCARD_HOSTS = {"0.0.0.0", "[::]", "::"}
_ENDPOINT = re.compile(
    r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<host>\[[^\]]+\]|[^/:\[\]]+):(?P<port>\d+)$"
)


def _check_endpoint(value: str) -> str:
    match = _ENDPOINT.match(value)
    if not match or not 0 <= int(match["port"]) <= 65535:
        raise ValueError(
            f"{value!r} is not a Zenoh endpoint PROTO/HOST:PORT such as tcp/10.0.0.5:7447 "
            "or tls/head.example.org:7447"
        )
    return value


Endpoint = Annotated[str, AfterValidator(_check_endpoint)]


def split_endpoint(endpoint: str) -> tuple[str, str, int]:
    """(protocol, host, port) of a checked endpoint."""
    match = _ENDPOINT.match(endpoint)
    if match is None:
        raise ValueError(f"not an endpoint: {endpoint!r}")
    return match["proto"], match["host"], int(match["port"])


def with_port(endpoint: str, port: int) -> str:
    proto, host, _ = split_endpoint(endpoint)
    return f"{proto}/{host}:{port}"


def is_seed(listen: str, host: HostSpec, seed: str) -> bool:
    """Whether the process of `host` listening on `listen` is the mesh's seed (it connects to
    nobody)."""
    if listen == seed:
        return True
    proto, listen_host, port = split_endpoint(listen)
    seed_proto, seed_host, seed_port = split_endpoint(seed)
    return (
        (proto, port) == (seed_proto, seed_port)
        and listen_host in WILDCARD_HOSTS
        and host.address == seed_host
    )


# --- the file ------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class NodeSpec(_Strict):
    """`count` processes of one role on a host."""

    role: Literal["coordinator", "trainer", "evaluator", "router"] = Field(
        description="the node each process runs"
    )
    count: int = Field(1, ge=1, le=4096, description="processes of this role")
    threads: int = Field(1, ge=1, le=4096, description="simulation threads of each worker")
    restart: Literal["never", "on-failure", "always"] = Field(
        "on-failure", description="when a process that ended is started again"
    )
    max_restarts: int = Field(3, ge=0, description="restarts of each process, at most")
    listen: Endpoint | None = Field(
        None,
        description="where these processes listen in a peer mesh, process k on port + k (port "
        "0: a free one each); default: the host's `listen`",
    )
    tensorboard: Path | None = Field(
        None,
        description="trainers: write each training's curves and PPO diagnostics to TensorBoard "
        "in LOGDIR/<run>/children/<agent> (`derl trainer --tensorboard`)",
    )

    @model_validator(mode="after")
    def _trainers_write_trainings(self) -> NodeSpec:
        if self.tensorboard is not None and self.role != "trainer":
            raise ValueError(
                f"tensorboard is a trainer's setting ({self.role} nodes train nothing)"
            )
        return self


class PeerMesh(_Strict):
    """Every node is a Zenoh peer: it listens on its host's endpoint and connects to `seed`."""

    kind: Literal["peer_mesh"]
    seed: Endpoint = Field(description="the endpoint every node connects to")


class RouterTopology(_Strict):
    """`derl router` on host `host` at `endpoint`; every node is a Zenoh client of it."""

    kind: Literal["router"]
    endpoint: Endpoint = Field(description="where the router listens")
    host: Id = Field(description="the host it runs on")


class HostSpec(_Strict):
    """One machine and the nodes it starts."""

    name: Id = Field(description="the host's name (`derl launch --host NAME`)")
    address: str = Field("localhost", min_length=1, description="for ssh; localhost = this host")
    ssh: bool | str = Field(False, description="start its nodes over ssh (true, or user@host)")
    listen: Endpoint | None = Field(None, description="where this host's nodes listen (mesh)")
    workdir: str | None = Field(None, description="directory the nodes start in (ssh hosts)")
    derl: str = Field("derl", min_length=1, description="the derl command on this host")
    zenoh_config: Path | None = Field(None, description="this host's Zenoh config (certificates)")
    nodes: list[NodeSpec] = Field(default_factory=list, description="the nodes it starts")

    @property
    def local_address(self) -> bool:
        return self.address in LOCAL_ADDRESSES

    def mesh_endpoints(self) -> list[str]:
        """Where each of this host's processes listens in a peer mesh, in order: process k of a
        node entry on the entry's `listen` port + k, else process k of the host on the host's
        `listen` port + k, else a free loopback port (port 0 stays 0: a free port each)."""
        endpoints: list[str] = []
        for spec in self.nodes:
            for k in range(spec.count):
                if spec.listen:
                    base, offset = spec.listen, k
                else:
                    base, offset = self.listen or LOOPBACK_ANY_PORT[0], len(endpoints)
                _, _, port = split_endpoint(base)
                endpoints.append(with_port(base, port + offset if port else 0))
        return endpoints

    @property
    def remote(self) -> str | None:
        """The ssh target when this host's nodes are started over ssh, else None."""
        if self.ssh is False or (self.ssh is True and self.local_address):
            return None
        return self.address if self.ssh is True else str(self.ssh)


class LaunchFile(_Strict):
    run: Id = Field(description="the run id (keys live under derl/<run>/)")
    run_dir: Path | None = Field(None, description="the coordinator's run directory")
    study: Path | None = Field(
        None,
        description="instead of a run: the study directory whose appendix D stage the "
        "coordinator runs with evaluator nodes (`profile` then names a study profile)",
    )
    study_runs: list[Path] = Field(
        [],
        description="the runs the study selects from, on the coordinator's host (the study "
        "is planned there at its first start; none: `derl study --plan-only` planned it)",
    )
    profile: str = Field("smoke", min_length=1, description="smoke | demo | paper | FILE.yaml")
    env: str | None = Field(
        None, description="world: ft, vt, mvt or a plugin task (overrides profile)"
    )
    seed: int | None = Field(None, ge=0, description="evolution seed (overrides profile)")
    settings: list[Annotated[str, Field(pattern=r"^[^=\s]+=")]] = Field(
        [], description="profile values changed, each `KEY=VALUE` as `--set` takes it"
    )
    topology: Annotated[
        PeerMesh | RouterTopology, Field(discriminator="kind", description="how the nodes connect")
    ]
    zenoh_config: Path | None = Field(None, description="Zenoh JSON5 config of every node")
    certs: Path | None = Field(
        None,
        description="folder written by `derl certs`: each node takes its own certificate and "
        "config (CERTS/<node>/zenoh.json5; wins over zenoh_config)",
    )
    hosts: list[HostSpec] = Field(min_length=1, description="the hosts and their nodes")

    @property
    def directory(self) -> Path:
        """The coordinator's directory: the run's or the study's."""
        directory = self.study if self.study is not None else self.run_dir
        assert directory is not None  # one of them (`_consistent`)
        return directory

    @model_validator(mode="after")
    def _consistent(self) -> LaunchFile:
        if (self.run_dir is None) == (self.study is None):
            raise ValueError("give `run_dir` (a run) or `study` (a study), one of them")
        if self.study_runs and self.study is None:
            raise ValueError("`study_runs` go with `study`")
        if self.study is not None and any(n.role == "trainer" for h in self.hosts for n in h.nodes):
            raise ValueError("a study trains no children: start evaluator nodes, not trainers")
        names = [h.name for h in self.hosts]
        if duplicated := sorted({n for n in names if names.count(n) > 1}):
            raise ValueError(f"host names must be unique: {', '.join(duplicated)} repeated")
        coordinators = [
            (h.name, n.count) for h in self.hosts for n in h.nodes if n.role == "coordinator"
        ]
        if sum(count for _, count in coordinators) != 1:
            raise ValueError(
                f"a run has exactly one coordinator (count 1); this file has "
                f"{sum(count for _, count in coordinators)}"
            )
        routers = [(h.name, n.count) for h in self.hosts for n in h.nodes if n.role == "router"]
        if isinstance(self.topology, RouterTopology):
            if any(n.listen for h in self.hosts for n in h.nodes):
                raise ValueError("a node's `listen` is for a peer mesh: in a router topology "
                                 "every node is a client of the router")  # fmt: skip
            if self.topology.host not in names:
                raise ValueError(f"router host {self.topology.host!r} is not among the hosts")
            if routers != [(self.topology.host, 1)]:
                raise ValueError(
                    f"the router topology needs one node `role: router` (count 1) on host "
                    f"{self.topology.host!r}, and no other router; found {routers or 'none'}"
                )
        else:
            if routers:
                raise ValueError("`role: router` nodes need `topology: {kind: router, ...}`")
            for host in self.hosts:
                unreachable = [n for n in host.nodes if (n.listen or host.listen) is None]
                if unreachable and not host.local_address:
                    raise ValueError(
                        f"host {host.name!r}: in a peer mesh every host needs a `listen` "
                        "endpoint the other hosts can reach (peers without one do not mesh)"
                    )
            seed = self.topology.seed
            if not any(is_seed(at, h, seed) for h in self.hosts for at in h.mesh_endpoints()):
                raise ValueError(
                    f"no node listens on the seed {self.topology.seed}: give the seed's host "
                    f"`listen: {self.topology.seed}` (its first node is the seed)"
                )
        return self

    def host(self, name: str) -> HostSpec:
        for host in self.hosts:
            if host.name == name:
                return host
        raise KeyError(
            f"no host {name!r} in this launch file; hosts: {[h.name for h in self.hosts]}"
        )


def load(path: Path) -> LaunchFile:
    """The launch file at `path`, or ValueError saying what is wrong with it (a pydantic
    ValidationError when it does not fit `LaunchFile`)."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"{path}: {error}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a launch file is a mapping (run, run_dir, topology, hosts ...)")
    return LaunchFile.model_validate(data)
