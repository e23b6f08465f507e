"""The references written from the code: the protocol and the configuration (docs/protocol.md,
docs/configuration.md: the models' JSON schemas, the key space, who publishes what and how) and
the modules (docs/modules.md: every package and module with its job, from their docstrings).

`DOCUMENTS` maps a document's name to the function that writes it; `derl schema --markdown NAME`
prints one, and tests/test_reference.py checks that the committed files are current.
"""

from __future__ import annotations

import inspect
import json
import math
from collections.abc import Callable
from typing import Final

from pydantic import BaseModel
from pydantic_core import to_jsonable_python

import derl.analysis.study
import derl.evolution.config
import derl.messages.codec
import derl.messages.keys
import derl.messages.schema
import derl.messages.types
from derl.analysis.study import STUDY_PROFILES, StudyConfig
from derl.evolution.config import PROFILES, EvolutionConfig, setting_keys
from derl.evolution.timing import TrainingTime
from derl.messages import (
    MESSAGE_TYPES,
    SCHEMA_CHANGES,
    SCHEMA_VERSION,
    Curve,
    KeySpace,
    MessageBase,
    ParentWeights,
    PopulationEntry,
)
from derl.messages.examples import examples
from derl.messages.keys import ARITY, PUBLISHERS, ROOT, ROUTES
from derl.messages.types import ID_PATTERN
from derl.nodes.launch.model import HostSpec, LaunchFile, NodeSpec, PeerMesh, RouterTopology
from derl.nodes.runtime.bus import congestion_control
from derl.nodes.tools.logs import base64_text, json_form
from derl.nodes.tools.module_tree import FOLDERS, module_tree
from derl.rl.config import PPOConfig, PPOHyperparameters
from derl.unimal.genome import Genome, Joint, Limb

PPO_ANCHOR: Final = "#ppoconfig"
HYPER_ANCHOR: Final = "#ppo-ppohyperparameters"
NESTED: Final = (Curve, PopulationEntry, ParentWeights, Genome, Limb, Joint)
LAUNCH_MODELS: Final = (LaunchFile, HostSpec, NodeSpec, PeerMesh, RouterTopology)

Links = dict[str, str]
"""Model name -> where it is documented."""


def command(name: str) -> str:
    """The shell command that rewrites document `name`."""
    return f"derl schema --markdown {name} > docs/{name}.md"


def _header(title: str, name: str) -> list[str]:
    return [
        f"# {title}",
        "",
        f"Generated from the code by `{command(name)}`; do not edit it by hand",
        "(tests/test_reference.py fails when it is out of date).",
        "",
    ]


# --- the protocol ----------------------------------------------------------------------------


def protocol() -> str:
    """docs/protocol.md: keys, publishers, congestion control, every message with an example."""
    links = {name: f"#{name.lower()}" for name in [*MESSAGE_TYPES, *(m.__name__ for m in NESTED)]}
    links[PPOConfig.__name__] = f"configuration.md{PPO_ANCHOR}"
    lines = _header("The wire protocol", "protocol")
    lines += [
        f"Schema version: **{SCHEMA_VERSION}**. Every payload is a msgpack map with "
        "`schema_version`, `type` (the message type) and `run`; a node refuses any other version, "
        "and a journal or recording whose channels say another version is refused as a whole "
        "(read or resume it with the derl that wrote it). What each version changed:",
        "",
        *(f"- {version}: {change}." for version, change in sorted(SCHEMA_CHANGES.items())),
        "",
        _markdown(inspect.getdoc(derl.messages.codec)),
        "",
        _markdown(inspect.getdoc(derl.messages.types)) + f" An id matches `{ID_PATTERN}`.",
        "",
        "## Keys",
        "",
        _markdown(inspect.getdoc(derl.messages.keys)),
        "",
        "| key | messages | published by | congestion control |",
        "| --- | --- | --- | --- |",
        *(_key_row(kind, links) for kind in ARITY),
        "",
        "BLOCK: a put waits while the link is congested, nothing is lost; DROP: it is dropped, "
        "and the next periodic one replaces it.",
        "",
        "## Messages",
        "",
        _markdown(inspect.getdoc(derl.messages.schema)),
        "",
        "Bytes travel as msgpack bin; the examples show them in base64.",
        "",
    ]
    for message in examples(run="run1", checkpoint_bytes=16):
        lines += _message_section(message, links)
    lines += ["## Nested types", ""]
    for model in NESTED:
        lines += [f"### {model.__name__}", "", _markdown(inspect.getdoc(model)), ""]
        lines += _fields_table(model, links, "field")
    lines.append(f"PPOConfig: see [configuration.md]({links[PPOConfig.__name__]}).")
    return "\n".join(lines) + "\n"


KEYS_WITHOUT_MESSAGES = {
    "alive": "liveliness token (no payload)",
    "checkpoint": "answer to a query: the agent's checkpoint file (bytes)",
}
"""What goes on a key kind that carries no message."""


def _key_row(kind: str, links: Links) -> str:
    types = [name for name, (k, _) in ROUTES.items() if k == kind]
    roles = ", ".join(PUBLISHERS[kind]) or "nobody: journaled only"
    if not types:
        return f"| `{_key_pattern(kind)}` | {KEYS_WITHOUT_MESSAGES[kind]} | {roles} | |"
    congestion = sorted({str(congestion_control(name)).rsplit(".", 1)[-1] for name in types})
    published = " or ".join(congestion) if PUBLISHERS[kind] else ""
    names = ", ".join(f"[{name}]({links[name]})" for name in types)
    return f"| `{_key_pattern(kind)}` | {names} | {roles} | {published} |"


def _key_pattern(kind: str) -> str:
    """``derl/<run>/<kind>/<id>...``, the ids named after the fields that fill them (or after
    the parameters of the `KeySpace` method of a kind without messages)."""
    ids = next((fields for k, fields in ROUTES.values() if k == kind), None)
    if ids is None:
        ids = tuple(inspect.signature(getattr(KeySpace, kind)).parameters)[1:]
    return "/".join((ROOT, "<run>", kind, *(f"<{name}>" for name in ids)))


def _message_section(message: MessageBase, links: Links) -> list[str]:
    model = type(message)
    data = json_form(message, base64_text)
    fields = [f"  {json.dumps(key)}: {json.dumps(value)}" for key, value in data.items()]
    return [
        f"### {message.type}",
        "",
        _markdown(inspect.getdoc(model)),
        "",
        f"Key: `{_key_pattern(ROUTES[message.type][0])}`.",
        "",
        *_fields_table(model, links, "field"),
        "```json",
        "{\n" + ",\n".join(fields) + "\n}",
        "```",
        "",
    ]


# --- the configuration -----------------------------------------------------------------------


def configuration() -> str:
    """docs/configuration.md: the profile models with the built-in profiles (a run's, a
    study's), the launch file."""
    links = {m.__name__: f"#{m.__name__.lower()}" for m in LAUNCH_MODELS}
    links[PPOConfig.__name__] = PPO_ANCHOR
    links[PPOHyperparameters.__name__] = HYPER_ANCHOR
    links[TrainingTime.__name__] = "#training_time-trainingtime"
    lines = _header("Configuration", "configuration")
    lines += [
        *_profiles(
            "Profiles",
            derl.evolution.config,
            EvolutionConfig,
            "`derl run --profile NAME|FILE.yaml` (and `derl coordinator`, and a launch file's "
            "`profile`) choose one; `--set KEY=VALUE` changes one setting of it (repeatable, e.g. "
            "`--set ppo.lr=1e-4 --set total=200`): a dotted key, the value read as YAML, checked "
            "with the rest, as in a file. An unknown key is an error that names the valid ones. "
            "`derl launch` takes no `--set`: its file names the profile, so a profile file holds "
            "the changes. The built-in profiles:",
            _profile_values(lambda p: p),
            links,
        ),
        "## ppo: PPOHyperparameters",
        "",
        _markdown(inspect.getdoc(PPOHyperparameters)),
        "",
        *_fields_table(PPOHyperparameters, links, "key", _profile_values(lambda p: p.ppo)),
        "## training_time: TrainingTime",
        "",
        _markdown(inspect.getdoc(TrainingTime)),
        "",
        *_fields_table(TrainingTime, links, "key", _profile_values(lambda p: p.training_time)),
        "## PPOConfig",
        "",
        _markdown(inspect.getdoc(PPOConfig)) + " Every job carries one (`TrainJob`, `EvalJob`).",
        "",
        *_fields_table(PPOConfig, links, "field"),
        *_profiles(
            "Study profiles",
            derl.analysis.study,
            StudyConfig,
            "`derl study --profile NAME|FILE.yaml` chooses one and `--set KEY=VALUE` changes one "
            "setting of it, as for a run (an unknown key is an error that names the valid ones); "
            f"its `ppo` is a [PPOHyperparameters]({HYPER_ANCHOR}). The built-in study profiles:",
            dict(STUDY_PROFILES),
            links,
        ),
        "## Launch files: LaunchFile",
        "",
        "`derl launch FILE` starts the nodes a launch file (YAML) places on each host; "
        "[launch/local.yaml](../launch/local.yaml) and "
        "[launch/cluster.example.yaml](../launch/cluster.example.yaml) are examples. An unknown "
        "key is an error that names the valid ones.",
        "",
    ]
    for model in LAUNCH_MODELS:
        doc = _markdown(inspect.getdoc(model)) if model.__doc__ else ""
        lines += [f"### {model.__name__}", "", *([doc, ""] if doc else [])]
        lines += _fields_table(model, links, "key")
    return "\n".join(lines).rstrip("\n") + "\n"


def _profiles(
    title: str,
    module: object,
    model: type[BaseModel],
    usage: str,
    values: dict[str, BaseModel],
    links: Links,
) -> list[str]:
    """A section on a profile model: its module's and its own docs, how a command chooses
    one, and its fields with each built-in profile's value."""
    return [
        f"## {title}: {model.__name__}",
        "",
        _markdown(inspect.getdoc(module)),
        "",
        _markdown(inspect.getdoc(model)),
        "",
        usage,
        "",
        *_fields_table(model, links, "key", values),
    ]


def _profile_values(pick: Callable[[EvolutionConfig], BaseModel]) -> dict[str, BaseModel]:
    """Column name -> the model whose values fill it, one per built-in profile."""
    return {name: pick(profile) for name, profile in PROFILES.items()}


# --- tables ----------------------------------------------------------------------------------


def _fields_table(
    model: type[BaseModel],
    links: Links,
    what: str,
    columns: dict[str, BaseModel] | None = None,
) -> list[str]:
    """One row per field: its name, type, default, its value in each of `columns`, description.
    A message's fields without a description of their own take MessageBase's; the rows are in
    `setting_keys`' order."""
    columns = columns or {}
    properties = model.model_json_schema()["properties"]
    inherited = MessageBase.model_fields if issubclass(model, MessageBase) else {}
    fields = {key: model.model_fields[key] for key in setting_keys(model)}
    head = [what, "type", "default", *columns, "description"]
    rows = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for name, field in fields.items():
        prop = properties[name]
        about = field.description or getattr(inherited.get(name), "description", None) or ""
        cells = [
            f"`{name}`",
            _type(prop, links),
            _default(field.get_default(call_default_factory=True), field.is_required()),
            *(_value(getattr(values, name)) for values in columns.values()),
            _cell(about),
        ]
        rows.append("| " + " | ".join(cells) + " |")
    return [*rows, ""]


def _default(value: object, required: bool) -> str:
    return "required" if required else _value(value)


def _value(value: object) -> str:
    if isinstance(value, BaseModel):
        return "its defaults" if value == type(value)() else "see below"
    return _cell(f"`{json.dumps(to_jsonable_python(value))}`")


def _type(node: dict, links: Links) -> str:
    """A JSON schema node in a few words: a type, its bounds, links to nested models."""
    if "$ref" in node:
        name = node["$ref"].rsplit("/", 1)[1]
        return f"[{name}]({links[name]})" if name in links else name
    for union in ("anyOf", "oneOf"):
        if union in node:
            return " or ".join(_type(member, links) for member in node[union])
    if "const" in node:
        return f"`{json.dumps(node['const'])}`"
    if "enum" in node:
        return " or ".join(f"`{json.dumps(value)}`" for value in node["enum"])
    kind = node.get("type", "any")
    if kind == "array":
        if "prefixItems" in node:
            text = "[" + ", ".join(_type(item, links) for item in node["prefixItems"]) + "]"
            return text  # a fixed-size tuple: its length is in the brackets
        return f"list of {_type(node.get('items', {}), links)}" + _bounds(
            node, "minItems", "maxItems", " items"
        )
    if kind == "string":
        if node.get("pattern") == ID_PATTERN:
            return "id"
        text = {"binary": "bytes", "path": "path"}.get(node.get("format", ""), "text")
        unit = " bytes" if text == "bytes" else " characters"
        return text + _bounds(node, "minLength", "maxLength", unit)
    text = {"integer": "int", "number": "float", "boolean": "bool"}.get(kind, kind)
    return text + _bounds(node, "minimum", "maximum")


def _bounds(node: dict, low: str, high: str, unit: str = "") -> str:
    """`` (≥ a, ≤ b)`` from the node's bounds (and its exclusive bounds, > and <)."""
    marks = {low: "≥", "exclusiveMinimum": ">", high: "≤", "exclusiveMaximum": "<"}
    parts = [f"{mark} {_number(node[key])}" for key, mark in marks.items() if key in node]
    if node.get(low) is not None and node.get(low) == node.get(high):
        parts = [_number(node[low])]
    return f" ({', '.join(parts)}{unit})" if parts else ""


def _number(value: float) -> str:
    """Large round numbers as powers (10^13, 2^64 − 1), the rest as they are."""
    if isinstance(value, int) and value >= 2**20:
        for base in (10, 2):
            for offset, suffix in ((0, ""), (1, " − 1")):
                exponent = round(math.log(value + offset, base))
                if base**exponent == value + offset:
                    return f"{base}^{exponent}{suffix}"
    return f"{value:,}" if isinstance(value, int) else repr(value)


# --- the modules -----------------------------------------------------------------------------


def modules() -> str:
    """docs/modules.md: every package folder and module, with its docstring's first sentence."""
    folders = ", ".join(f"`{f}/` is `{p}`" for p, f in FOLDERS.items() if p != f)
    lines = _header("The modules", "modules")
    lines += [
        f"derl installs one package, `derl`; in the repository {folders}. Every package and "
        "module with its job (the first sentence of its docstring); how they fit together is "
        "in [architecture.md](architecture.md).",
        "",
        "| file | its job |",
        "| --- | --- |",
    ]
    lines += [f"| `{entry.path}` | {_cell(entry.job)} |" for entry in module_tree()]
    return "\n".join(lines) + "\n"


# --- text ------------------------------------------------------------------------------------


def _markdown(docstring: str | None) -> str:
    """A docstring as Markdown: paragraphs kept, lines joined, ``code`` as `code`."""
    paragraphs = (docstring or "").replace("``", "`").split("\n\n")
    return "\n\n".join(" ".join(p.split()) for p in paragraphs)


def summary(model: type) -> str:
    """The first paragraph of a model's docstring, in one line of Markdown."""
    return _markdown(inspect.getdoc(model)).split("\n\n")[0]


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


DOCUMENTS: Final[dict[str, Callable[[], str]]] = {
    "protocol": protocol,
    "configuration": configuration,
    "modules": modules,
}
"""Document name (docs/NAME.md) -> the function that writes it."""
