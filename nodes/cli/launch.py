"""`derl launch FILE`: start the nodes of a launch file (`nodes.launch`) on their hosts."""

from __future__ import annotations

import argparse
import logging
import signal
from pathlib import Path

from pydantic import ValidationError

from derl.nodes.cli.options import fail, fail_invalid, profile_from
from derl.nodes.launch.commands import dry_run_text, plan
from derl.nodes.launch.model import LaunchFile, load
from derl.nodes.launch.supervisor import Supervisor

log = logging.getLogger("derl.launch")


def register(commands: argparse._SubParsersAction) -> None:
    launch = commands.add_parser(
        "launch",
        help="start the nodes of a launch file (this host's, and others' over ssh)",
        description="Start the nodes a launch file places on this host, and those of its ssh "
        "hosts over ssh; restart them by their policy; stop them all on Ctrl-C or SIGTERM.",
    )
    launch.add_argument("file", type=Path, help="launch file (YAML), e.g. launch/local.yaml")
    launch.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="NAME",
        help="start this host's nodes here, never over ssh (repeatable; default: the host "
        "named `local` or after this machine, else every host without ssh, and the ssh "
        "hosts' nodes over ssh)",
    )
    launch.add_argument("--no-ssh", action="store_true", help="do not start ssh hosts' nodes")
    launch.add_argument("--dry-run", action="store_true", help="print every command, start none")
    launch.add_argument("--log-dir", type=Path, help="node logs (default: RUN_DIR/logs)")
    launch.set_defaults(handler=_launch)


def _launch(args: argparse.Namespace) -> int:
    try:
        launch = load(args.file)
        commands = plan(launch, args.file, args.host, ssh=not args.no_ssh)
    except ValidationError as error:
        fail_invalid(f"{args.file} is not a valid launch file", error, LaunchFile)
    except ValueError as error:
        fail(str(error))
    except KeyError as error:
        fail(error.args[0])
    if not commands:
        fail(f"no nodes to start from {args.file} on this host")
    if args.dry_run:
        print(dry_run_text(commands))
        return 0
    if any(c.role == "coordinator" and c.remote is None for c in commands):
        profile_from(argparse.Namespace(profile=launch.profile, set=[], env=launch.env,
                                        seed=launch.seed))  # fmt: skip
    supervisor = Supervisor(commands, args.log_dir or launch.directory / "logs")
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):  # SIGHUP: our ssh session ended
        signal.signal(sig, lambda *_: supervisor.stop.set())
    hosts = sorted({c.host for c in commands})
    log.info("run %s: %d node processes of %s; logs in %s", launch.run, len(commands),
             ", ".join(hosts), supervisor.log_dir)  # fmt: skip
    return supervisor.run()
