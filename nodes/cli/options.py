"""Flags shared by the commands: how a node joins the bus, and which profile a run uses."""

from __future__ import annotations

import argparse
from pathlib import Path

from nodes.runtime.bus import ZenohOptions


def add_bus_arguments(parser: argparse.ArgumentParser, run_required: bool = True) -> None:
    group = parser.add_argument_group("bus")
    group.add_argument("--run", required=run_required, help="run id (keys live under derl/<run>/)")
    for flag, example in (("--listen", "tcp/0.0.0.0:7447"), ("--connect", "tcp/10.0.0.5:7447")):
        group.add_argument(
            flag,
            action="append",
            default=[],
            metavar="EP",
            help=f"endpoint to {flag[2:]} {'to' if flag == '--connect' else 'on'}, "
            f"e.g. {example} (repeatable)",
        )
    group.add_argument("--mode", choices=["peer", "client"], default="peer")
    group.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config (TLS, ACL, ...)")
    group.add_argument("--multicast", action="store_true", help="turn multicast scouting on")


def options_from(args: argparse.Namespace, mode: str | None = None) -> ZenohOptions:
    return ZenohOptions(
        mode=mode or args.mode,
        listen=tuple(args.listen),
        connect=tuple(args.connect),
        multicast=args.multicast,
        config_file=args.zenoh_config,
    )


def add_profile_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="smoke", help="smoke | demo | paper | FILE.yaml")
    parser.add_argument("--env", choices=["ft", "vt", "mvt"], help="world (overrides the profile)")


def profile_from(args: argparse.Namespace):  # -> EvolutionConfig
    """The run's profile from --profile/--env, or exit with the reason it is not valid."""
    from derl.evolution import load_profile

    try:
        return load_profile(args.profile, world=args.env)
    except (ValueError, OSError) as error:
        raise SystemExit(f"derl: profile {args.profile!r} is not valid:\n{error}") from None
