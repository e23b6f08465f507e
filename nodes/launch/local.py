"""The graph of a run on one host: `local.yaml` beside this module (the repository's
`launch/local.yaml`), the one declaration of which nodes `derl run` and `derl study` start, here
with a run's own numbers (its id and directory, profile, port and worker counts).
"""

from __future__ import annotations

from pathlib import Path

from derl.nodes.launch.model import LaunchFile, load

LOCAL_FILE = Path(__file__).with_name("local.yaml")


def local_launch(
    run: str,
    endpoint: str,
    workers: dict[str, int],
    tensorboard: Path | None = None,
    **coordinator: object,
) -> LaunchFile:
    """`local.yaml` for run `run`: its coordinator listening on `endpoint` (the seed every other
    node connects to), `workers[role]` processes of each worker role the file declares (none or
    0: left out), its trainers writing each training to `tensorboard` if given, and the
    coordinator's settings (`run_dir` or `study`, `profile`, `env`, `seed`, `settings`,
    `study_runs`) as given."""
    graph = load(LOCAL_FILE)
    data = graph.model_dump()
    data.update(run=run, run_dir=None, topology={"kind": "peer_mesh", "seed": endpoint})
    data.update(coordinator)
    for host in data["hosts"]:
        nodes = []
        for spec in host["nodes"]:
            if spec["role"] == "coordinator":
                nodes.append({**spec, "listen": endpoint})
            elif workers.get(spec["role"]):
                board = {"tensorboard": tensorboard} if spec["role"] == "trainer" else {}
                nodes.append({**spec, "count": workers[spec["role"]], **board})
        host["nodes"] = nodes
    return LaunchFile.model_validate(data)
