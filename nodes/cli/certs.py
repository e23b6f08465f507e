"""`derl certs FILE`: the CA, per-node certificates and access control of a launch file (without
FILE: a CA alone, with which each start of a Slurm job issues its nodes' identities)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pydantic import ValidationError

from derl.nodes.cli.options import fail, fail_invalid
from derl.nodes.launch.identities import MONITOR, make_ca, write_identities
from derl.nodes.launch.model import LaunchFile, load


def register(commands: argparse._SubParsersAction) -> None:
    certs = commands.add_parser(
        "certs",
        help="write a launch file's CA, one certificate per node and their Zenoh configs",
        description="Write a new CA, one certificate per node of the launch file (common name "
        "= its node id) and a monitor certificate, each with a Zenoh config: mutual TLS, and "
        "access control under which a node may publish only on its own keys. With `certs: "
        "DIR` in the launch file, `derl launch` gives each node its own config.",
    )
    certs.add_argument(
        "file",
        type=Path,
        nargs="?",
        help="launch file (YAML) with tls/ endpoints; none: a CA alone, for `derl slurm --certs`",
    )
    certs.add_argument("--out", type=Path, help="folder (default: the launch file's `certs`)")
    certs.set_defaults(handler=_certs)


def _certs(args: argparse.Namespace) -> int:
    if args.file is None:
        if args.out is None:
            fail("give a launch file, or --out DIR for a CA alone")
        _refuse_a_second_ca(args.out)
        args.out.mkdir(parents=True, exist_ok=True)
        make_ca(args.out, f"derl {args.out.resolve().name} CA")
        print(f"CA in {args.out} (ca.pem; keep ca.key to yourself): a Slurm job issues its "
              f"nodes' identities with it (`derl slurm --certs {args.out}`)")  # fmt: skip
        return 0
    try:
        launch = load(args.file)
    except ValidationError as error:
        fail_invalid(f"{args.file} is not a valid launch file", error, LaunchFile)
    except ValueError as error:
        fail(str(error))
    out = args.out or launch.certs
    if out is None:
        fail(f"{args.file} names no `certs:` folder: give --out DIR")
    _refuse_a_second_ca(out)
    configs = write_identities(launch, out)
    print(f"CA and {len(configs) - 1} node identities in {out}; a monitor's: {out / MONITOR}")
    print("copy to every host, at the same path: ca.pem and the folders of its nodes; keep ca.key")
    return 0


def _refuse_a_second_ca(out: Path) -> None:
    if (out / "ca.key").exists():
        fail(f"{out} already holds a CA: remove it first (its certificates would all change)")
