"""The wire: every message round-trips, bad values and bad payloads give one error type, keys."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import typing

import msgpack
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from derl.messages import (
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    DecodeError,
    FitnessReport,
    FitnessSource,
    InvalidKey,
    KeySpace,
    MessageBase,
    TrainJob,
    decode,
    encode,
    kind_of,
    parse,
)
from derl.messages.examples import GENOME, examples
from derl.messages.keys import ARITY, ROUTES

SAMPLES = examples("run1", 3)
PAYLOADS = [encode(m) for m in SAMPLES]


def _dump(msg: MessageBase) -> dict[str, typing.Any]:
    return msg.model_dump(mode="python")


def _set(raw: dict[str, typing.Any], path: str, value: object) -> dict[str, typing.Any]:
    """A copy of `raw` with the (dotted) field `path` set to `value`."""
    head, _, rest = path.partition(".")
    out = dict(raw)
    out[head] = _set(raw[head], rest, value) if rest else value
    return out


def _sample(type_name: str) -> MessageBase:
    return next(m for m in SAMPLES if m.type == type_name)


# --- models and codec --------------------------------------------------------------------------


def test_one_example_per_type_and_every_type_is_routed() -> None:
    assert [m.type for m in SAMPLES] == list(MESSAGE_TYPES)
    assert set(ROUTES) == set(MESSAGE_TYPES)
    assert {kind for kind, _ in ROUTES.values()} <= set(ARITY)


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: m.type)
def test_round_trip_is_exact(msg: MessageBase) -> None:
    payload = encode(msg)
    back = decode(payload, type(msg))
    assert back == msg
    assert type(back) is type(msg)
    assert encode(back) == payload
    assert msg.schema_version == SCHEMA_VERSION


def test_genome_and_checkpoint_survive() -> None:
    report = examples("r", 5, checkpoint_bytes=900_000)[5]
    assert isinstance(report, FitnessReport)
    back = decode(encode(report), FitnessReport)
    assert back.checkpoint == report.checkpoint and len(back.checkpoint) == 900_000
    job = decode(encode(_sample("TrainJob")), TrainJob)
    assert job.genome == GENOME and job.genome.num_limbs == 4


def test_missing_measure_is_nan_and_survives() -> None:
    report = _sample("FitnessReport").model_copy(update={"energy": math.nan})
    back = FitnessReport.model_validate(decode(encode(report)).model_dump())
    assert math.isnan(back.energy) and encode(back) == encode(report)


ENCODED_ELSEWHERE = (
    "import sys, msgpack; from derl.messages import encode; "
    "from derl.messages.examples import examples; "
    "sys.stdout.buffer.write(msgpack.packb([encode(m) for m in examples('run1', 3)]))"
)


def test_encoding_is_deterministic_across_processes() -> None:
    """The same messages encode to the same bytes in processes whose string hashes differ (an
    order that follows a set's or a hash's would differ between them, never within one)."""
    argv = [sys.executable, "-c", ENCODED_ELSEWHERE]
    encoders = [
        subprocess.Popen(argv, stdout=subprocess.PIPE, env={**os.environ, "PYTHONHASHSEED": seed})
        for seed in ("1", "2")
    ]
    outputs = [encoder.communicate(timeout=60)[0] for encoder in encoders]
    assert [encoder.returncode for encoder in encoders] == [0, 0]
    assert [msgpack.unpackb(output) for output in outputs] == [PAYLOADS, PAYLOADS]


def test_messages_are_frozen() -> None:
    with pytest.raises(ValidationError):
        _sample("Ack").node = "other"  # type: ignore[misc]


def test_fitness_source_matches_lifetime_learning() -> None:
    from derl.rl.episodes import FitnessSource as RLFitnessSource

    assert typing.get_args(FitnessSource) == typing.get_args(RLFitnessSource)


BAD_VALUES = [
    ("WorkerReady", "role", "coordinator"),
    ("WorkerReady", "pid", 0),
    ("WorkerReady", "nthread", 0),
    ("WorkerReady", "node", ""),
    ("WorkerReady", "node", "a/b"),
    ("WorkerReady", "node", "a*"),
    ("WorkerReady", "run", "run$1"),
    ("WorkerReady", "node", "x" * 129),
    ("TrainJob", "ppo.seed", 2**64),
    ("TrainJob", "ppo.total_steps", 0),
    ("TrainJob", "ppo.num_envs", 0),
    ("TrainJob", "ppo.gamma", 2.0),
    ("TrainJob", "lease_s", 0.0),
    ("TrainJob", "lease_s", math.inf),
    ("TrainJob", "task", "a b"),
    ("TrainJob", "genome.head_density", 650),
    ("TrainJob", "genome.limbs", ({"id": 0},)),
    ("EvalJob", "agent", "?"),
    ("Tournament", "fitness", (1.0, 2.0)),
    ("Tournament", "fitness", (1.0, math.nan, 1.0)),
    ("Tournament", "mutation_seed", -1),
    ("TrainJob", "parent", None),  # its mutation needs a parent
    ("TrainJob", "mutation", None),  # a parent needs the mutation
    ("TrainJob", "mutation", "teleport"),
    ("FitnessReport", "genome.limbs", ({"id": 0},)),
    ("Tournament", "contestants", ()),
    ("Tournament", "iteration", -1),
    ("TrainProgress", "env_steps", 10_000_000),
    ("TrainProgress", "recent_return", math.inf),
    ("TrainProgress", "steps_per_s", -1.0),
    ("FitnessReport", "fitness", math.nan),
    ("FitnessReport", "fitness", -math.inf),
    ("FitnessReport", "fitness_source", "guess"),
    ("FitnessReport", "energy", -1.0),
    ("FitnessReport", "cost_of_work", math.inf),
    ("FitnessReport", "mass", 0.0),
    ("FitnessReport", "checkpoint", "not bytes"),
    ("FitnessReport", "curve.returns", (1.0,)),
    ("FitnessReport", "curve.env_steps", (10, 5)),
    ("Ack", "of", "TrainJob"),
    ("EvalResult", "reward", math.nan),
    ("PopulationSnapshot", "birth_counter", 1),
    ("PopulationSnapshot", "members", ({"agent": "a", "fitness": 1.0, "birth": 0},) * 2),
    ("RunStatus", "best_agent", None),
    ("RunStatus", "target", -1),
    ("RunStatus", "in_flight", -1),
]


@pytest.mark.parametrize(("type_name", "field", "value"), BAD_VALUES)
def test_out_of_range_values_are_rejected(type_name: str, field: str, value: object) -> None:
    raw = _set(_dump(_sample(type_name)), field, value)
    with pytest.raises(ValidationError):
        MESSAGE_TYPES[type_name].model_validate(raw)
    if value == 2**64:
        return  # msgpack cannot carry it: only the model sees it
    reason = f"invalid {type_name}: ({field.split('.')[0]}|Value error)"
    with pytest.raises(DecodeError, match=reason):
        decode(msgpack.packb(raw))


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: m.type)
def test_unknown_keys_are_rejected(msg: MessageBase) -> None:
    raw = {**_dump(msg), "surprise": 1}
    with pytest.raises(ValidationError):
        type(msg).model_validate(raw)
    with pytest.raises(DecodeError, match="surprise"):
        decode(msgpack.packb(raw))


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        ({**_dump(SAMPLES[0]), "schema_version": 4}, "schema version 4, expected 5"),
        ({k: v for k, v in _dump(SAMPLES[0]).items() if k != "schema_version"}, "schema version"),
        ({**_dump(SAMPLES[0]), "type": "Teleport"}, "unknown message type 'Teleport'"),
        ({**_dump(SAMPLES[0]), "type": [1, 2]}, "unknown message type"),
        ({k: v for k, v in _dump(SAMPLES[0]).items() if k != "type"}, "no message type"),
        ([1, 2, 3], "not a map"),
    ],
)
def test_bad_envelopes_say_why(raw: object, reason: str) -> None:
    with pytest.raises(DecodeError, match=reason):
        decode(msgpack.packb(raw))


@pytest.mark.parametrize("payload", [b"", b"\xc1", PAYLOADS[1][:-1], PAYLOADS[0] + b"\x00"])
def test_broken_msgpack_is_a_decode_error(payload: bytes) -> None:
    with pytest.raises(DecodeError, match="not msgpack"):
        decode(payload)


def test_expected_type_is_enforced() -> None:
    with pytest.raises(DecodeError, match="expected FitnessReport, got Ack"):
        decode(encode(_sample("Ack")), FitnessReport)


def _reason(payload: bytes) -> str | None:
    """Why `payload` is refused, or None when it is a valid message."""
    try:
        decode(payload)
    except DecodeError as error:
        return str(error)
    return None


# every reason `decode` gives, by the kind of fault it names; a validator tripping over absurd
# input ("invalid message: ...") is in none of them
NOT_MSGPACK = r"not msgpack: "
NOT_A_MAP = r"not a map but \w+$"
VERSION = rf"schema version .*, expected {SCHEMA_VERSION}$"
TYPE = r"unknown message type |no message type$"
REASONS = re.compile("|".join((NOT_MSGPACK, NOT_A_MAP, VERSION, TYPE, r"invalid [A-Z]\w+: ")))


def _invalid(type_name: str, field: str) -> str:
    """The reason for a bad (dotted) `field` of `type_name`: that field, or a check across the
    fields of the message or of the nested model holding it."""
    holder = rf"{re.escape(field.rpartition('.')[0])}: " if "." in field else ""
    return rf"invalid {type_name}: ({re.escape(field)}[.:]|{holder}Value error, |Value error, )"


FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FUZZ
@given(st.binary(max_size=512))
def test_random_bytes_say_why(payload: bytes) -> None:
    try:
        raw = msgpack.unpackb(payload, use_list=False)
    except Exception:
        expected = NOT_MSGPACK
    else:  # bytes that happen to be msgpack: almost never a map, never one with a version
        expected = NOT_A_MAP if not isinstance(raw, dict) else VERSION
    reason = _reason(payload)
    assert reason is not None and re.match(expected, reason), reason


@FUZZ
@given(st.sampled_from(PAYLOADS), st.data())
def test_mutated_payloads_say_why(payload: bytes, data: st.DataObject) -> None:
    buf = bytearray(payload)
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(buf) - 1))
        action = data.draw(st.sampled_from(["flip", "byte", "cut", "insert"]))
        if action == "flip":
            buf[at] ^= 1 << data.draw(st.integers(0, 7))
        elif action == "byte":
            buf[at] = data.draw(st.integers(0, 255))
        elif action == "cut":
            del buf[at:]
            break
        else:
            buf[at:at] = data.draw(st.binary(min_size=1, max_size=9))
    reason = _reason(bytes(buf))
    assert reason is None or REASONS.match(reason), reason


JUNK = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner),
    max_leaves=12,
)


@FUZZ
@given(st.sampled_from(SAMPLES), st.data(), JUNK)
def test_junk_in_any_field_names_the_field(
    msg: MessageBase, data: st.DataObject, junk: object
) -> None:
    raw = _dump(msg)
    field = data.draw(st.sampled_from(sorted(raw)))
    if isinstance(raw[field], dict):  # reach into nested models (genome, curve)
        field = f"{field}.{data.draw(st.sampled_from(sorted(raw[field])))}"
    raw = _set(raw, field, junk)
    reason = _reason(msgpack.packb(raw))
    if reason is None:
        return  # junk that is a valid value of that field
    expected = {"schema_version": VERSION, "type": TYPE}.get(field, _invalid(msg.type, field))
    assert re.match(expected, reason), (field, reason)


@FUZZ
@given(st.sampled_from(SAMPLES), st.data())
def test_a_missing_field_is_named(msg: MessageBase, data: st.DataObject) -> None:
    fields = type(msg).model_fields
    field = data.draw(st.sampled_from(sorted(f for f in fields if fields[f].is_required())))
    raw = {k: v for k, v in _dump(msg).items() if k != field}
    expected = {"schema_version": VERSION, "type": TYPE}.get(
        field, rf"invalid {msg.type}: {field}: Field required$"
    )
    reason = _reason(msgpack.packb(raw))
    assert reason is not None and re.match(expected, reason), reason


@FUZZ
@given(st.dictionaries(st.text(max_size=12), JUNK, max_size=6), st.sampled_from(list(ROUTES)))
def test_junk_maps_say_why(raw: dict[str, object], type_name: str) -> None:
    reason = _reason(msgpack.packb({"schema_version": SCHEMA_VERSION, "type": type_name, **raw}))
    if "schema_version" in raw:
        expected = rf"{VERSION}|invalid "
    elif "type" in raw:
        expected = rf"{TYPE}|invalid "
    else:  # required fields missing, unknown ones given
        expected = rf"invalid {type_name}: "
    assert reason is not None and re.match(expected, reason), reason


def test_deep_nesting_is_a_decode_error() -> None:
    for depth in (100, 10_000):
        with pytest.raises(DecodeError):
            decode(b"\x91" * depth + b"\x00")


# --- keys --------------------------------------------------------------------------------------

KS = KeySpace("run1")
BUILT = [
    (KS.alive("trainer", "t1"), "alive", ("trainer", "t1")),
    (KS.ready("t1"), "ready", ("t1",)),
    (KS.job("t1"), "job", ("t1",)),
    (KS.tournament("a12"), "tournament", ("a12",)),
    (KS.progress("n1", "a12"), "progress", ("n1", "a12")),
    (KS.fitness("n1", "a12"), "fitness", ("n1", "a12")),
    (KS.births("a12"), "births", ("a12",)),
    (KS.ack("t1"), "ack", ("t1",)),
    (KS.eval("n1", "a12", "patrol"), "eval", ("n1", "a12", "patrol")),
    (KS.population(), "population", ()),
    (KS.status(), "status", ()),
]


@pytest.mark.parametrize(("key", "kind", "parts"), BUILT, ids=lambda v: str(v))
def test_built_keys_parse_back_and_are_zenoh_keys(
    key: str, kind: str, parts: tuple[str, ...]
) -> None:
    assert key == "/".join(("derl", "run1", kind, *parts))
    assert parse(key) == ("run1", kind, parts)
    expr = zenoh.KeyExpr(key)
    assert zenoh.KeyExpr(KS.all(kind)).includes(expr)
    assert zenoh.KeyExpr(KS.everything()).includes(expr)
    assert not zenoh.KeyExpr(KeySpace("run2").everything()).intersects(expr)


def test_wildcards() -> None:
    assert KS.all("fitness") == "derl/run1/fitness/*/*"
    assert KS.all("fitness", "n1") == "derl/run1/fitness/n1/*"
    assert KS.all("alive", "trainer") == "derl/run1/alive/trainer/*"
    assert KS.all("eval") == "derl/run1/eval/*/*/*"
    assert KS.all("status") == "derl/run1/status"
    assert KS.everything() == "derl/run1/**"
    assert KS.family("fitness") == "derl/run1/fitness"


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: m.type)
def test_messages_route_to_their_kind(msg: MessageBase) -> None:
    kind, fields = ROUTES[msg.type]
    assert kind == kind_of(msg)
    assert parse(KS.key_for(msg)) == ("run1", kind, tuple(getattr(msg, f) for f in fields))
    with pytest.raises(InvalidKey):
        KeySpace("run2").key_for(msg)


UNSAFE = ["", "a/b", "*", "**", "a$b", "q?", "#", "a b", "é", "x" * 129, "a\n"]


@pytest.mark.parametrize("bad", UNSAFE)
def test_unsafe_ids_are_rejected(bad: str) -> None:
    with pytest.raises(InvalidKey):
        KeySpace(bad)
    with pytest.raises(InvalidKey):
        KS.fitness("n1", bad)
    with pytest.raises(InvalidKey):
        KS.alive(bad, "n")
    with pytest.raises(InvalidKey):
        KS.all("eval", bad)


@pytest.mark.parametrize(
    "key",
    [
        "derl/run1/teleport/x",
        "derl/run1/fitness",
        "derl/run1/fitness/a/b/c",
        "derl/run1/status/x",
        "derl/run1/fitness/*",
        "derl//status",
        "other/run1/status",
        "derl/run1",
        "",
        "derl/run1/eval/a12/",
    ],
)
def test_parse_rejects_foreign_keys(key: str) -> None:
    with pytest.raises(InvalidKey):
        parse(key)


def test_unknown_kinds_are_rejected_when_building() -> None:
    for build in (lambda: KS.key("teleport"), lambda: KS.all("x"), lambda: KS.family("x")):
        with pytest.raises(InvalidKey, match="unknown kind"):
            build()
    with pytest.raises(InvalidKey, match="3 id segments"):
        KS.key("eval", "a")
