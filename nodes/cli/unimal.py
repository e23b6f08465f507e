"""`derl unimal sample|show|render|count`: make, inspect and draw bodies of the design space."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rich.console import Console
from rich.progress import track
from rich.table import Table

from derl.nodes.cli.options import at_least_one, fail, output_directory, output_file
from derl.nodes.errors import USAGE

console = Console()


def register(commands: argparse._SubParsersAction) -> None:
    unimal = commands.add_parser("unimal", help="sample, inspect and render UNIMAL bodies")
    sub = unimal.add_subparsers(dest="unimal_command", required=True, metavar="ACTION")

    sample = sub.add_parser("sample", help="write N valid random bodies (genome JSON + MJCF)")
    sample.add_argument("--n", type=at_least_one, default=16, help="number of bodies (default 16)")
    sample.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sample.add_argument("--out", type=Path, required=True, help="output directory")
    sample.set_defaults(handler=_sample)

    show = sub.add_parser("show", help="print a body's descriptors")
    show.add_argument("file", type=Path, help="genome JSON file")
    show.add_argument("--json", action="store_true", help="print JSON instead of a table")
    show.set_defaults(handler=_show)

    render = sub.add_parser("render", help="draw a body, or a directory of bodies as a grid")
    render.add_argument(
        "path",
        type=Path,
        help="genome JSON file, or a directory of them (e.g. a run's best/ folder)",
    )
    render.add_argument("--out", type=Path, required=True, help="PNG file to write")
    render.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    render.set_defaults(handler=_render)

    count = sub.add_parser("count", help="count the distinct bodies of the design space")
    count.add_argument("--max-limbs", type=int, default=10)
    count.set_defaults(handler=_count)


def load_genome(path: Path):  # -> Genome
    """A genome from a JSON file, or exit with a clear message."""
    from pydantic import ValidationError

    from derl.unimal import Genome
    from derl.validation import problems

    try:
        return Genome.model_validate_json(path.read_text())
    except ValidationError as error:
        fail(f"{path} is not a valid genome: {problems(error)}")
    except FileNotFoundError:
        fail(f"{path}: no such file", USAGE)
    except OSError as error:
        fail(f"cannot read {path}: {error.strerror}")


def _sample(args: argparse.Namespace) -> int:
    import numpy as np

    from derl.unimal import to_mjcf
    from derl.unimal.sampling import iter_population

    output_directory(args.out)
    population = iter_population(np.random.default_rng(args.seed))
    table = Table("file", "limbs", "DoF", title=f"{args.n} bodies in {args.out}")
    for index in track(range(args.n), description="sampling bodies", console=console):
        genome = next(population)
        stem = args.out / f"unimal_{index:04d}"
        stem.with_suffix(".json").write_text(genome.model_dump_json(indent=2) + "\n")
        stem.with_suffix(".xml").write_text(to_mjcf(genome))
        table.add_row(stem.with_suffix(".json").name, str(genome.num_limbs), str(genome.dof))
    console.print(table)
    return 0


def _show(args: argparse.Namespace) -> int:
    from derl.unimal import describe

    descriptors = describe(load_genome(args.file))
    if args.json:
        print(descriptors.model_dump_json(indent=2))
        return 0
    table = Table("descriptor", "value", title=str(args.file))
    for name, value in descriptors.model_dump().items():
        table.add_row(name, f"{value:.4g}" if isinstance(value, float) else str(value))
    console.print(table)
    return 0


def _render(args: argparse.Namespace) -> int:
    from derl.agent_folder import TASK_FILES
    from derl.unimal.render import render_body, render_grid, save_png

    width, height = args.size
    output_file(args.out, "--out")
    if args.path.is_dir():  # a trained body's folder also holds its task and settings: not bodies
        files = sorted(f for f in args.path.rglob("*.json") if f.name not in TASK_FILES)
        if not files:
            fail(f"no genome JSON files in {args.path}")
        image = render_grid([load_genome(f) for f in files], width, height)
    else:
        image = render_body(load_genome(args.path), width, height)
    save_png(image, args.out)
    console.print(f"wrote {args.out} ({image.shape[1]}x{image.shape[0]})")
    return 0


def _count(args: argparse.Namespace) -> int:
    from derl.unimal.count import count_design_space, joint_configurations

    result = count_design_space(args.max_limbs)
    summary = {
        "bodies_with_1_to_max_limbs": f"{result.total:.3e}",
        "shapes_only (tree + directions)": f"{result.shapes:.3e}",
        "joint_configurations_per_limb": joint_configurations(),
        "paper_estimate": "1e18",
        "by_limbs": {n: f"{c:.3e}" for n, c in enumerate(result.by_limbs) if n},
    }
    print(json.dumps(summary, indent=2))
    return 0
