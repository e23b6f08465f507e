"""`derl foxglove` against a real WebSocket client: a Zenoh peer (loopback, multicast off, a fresh
port and run id) stands in for the coordinator, answering the births query with an earlier birth
and publishing new ones; the bridge serves them, and a `websockets` client speaking the Foxglove
protocol (advertise, subscribe, binary messageData) receives each birth's JSON and the summary;
every advertised schema is one the viewers' parser reads (tests/viewer_parser.py)."""

from __future__ import annotations

import asyncio
import json
import re
import struct
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import foxglove
import pytest
import websockets
import zenoh
from nodes_fixtures import free_port
from viewer_parser import parse_json_schema

from derl.messages import Birth, TrainProgress, encode
from derl.messages.examples import examples
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.tools.foxglove import SUMMARY_TOPIC, TOPICS, Bridge, RunSummary, serve
from derl.nodes.tools.logs import base64_text, json_form, json_schema
from derl.nodes.tools.viewer_schema import viewer_schema

LAYOUT = Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json"
SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk 0.30 accepts (formerly foxglove.websocket.v1)
MESSAGE_DATA = 1  # binary opcode: subscription id (u32), receive time (u64), payload


def _birth(run: str, index: int) -> Birth:
    birth = next(m for m in examples(run, 0) if isinstance(m, Birth))
    return birth.model_copy(
        update={"birth": index, "agent": f"a{index}", "fitness": 10.0 + index * (-1) ** index}
    )


@pytest.fixture
def coordinator() -> Iterator[tuple[str, Bus]]:
    """A peer on a fresh endpoint that answers the births query with birth 0 and nothing else."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(ZenohOptions(listen=(endpoint,))) as session:
        bus = Bus(session, f"f{uuid.uuid4().hex[:10]}")
        first = _birth(bus.run, 0)

        def answer(query: zenoh.Query) -> None:
            query.reply(bus.keys.births(first.agent), encode(first))

        queryable = session.declare_queryable(bus.keys.all("births"), answer)
        yield endpoint, bus
        queryable.undeclare()


@pytest.fixture
def bridge(coordinator: tuple[str, Bus]) -> Iterator[int]:
    """`serve` on a free port in a thread, connected to the coordinator; its port."""
    endpoint, bus = coordinator
    port = free_port()
    up, stop = threading.Event(), threading.Event()
    thread = threading.Thread(
        target=serve,
        args=(ZenohOptions(connect=(endpoint,)), bus.run, "127.0.0.1", port, stop),
        kwargs={"started": lambda run, server: up.set()},
        daemon=True,
    )
    thread.start()
    try:
        assert up.wait(30), "the bridge did not start"
        yield port
    finally:
        stop.set()
        thread.join(15)
    assert not thread.is_alive()


async def _watch(port: int, bus: Bus) -> tuple[dict[str, dict], dict, list[dict], dict]:
    """Subscribe to the births and the summary; publish births until one comes back. The
    advertised channels by topic, the first birth received, every birth received, a summary."""
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
        channels: dict[str, dict] = {}
        while not {*TOPICS.values(), SUMMARY_TOPIC} <= channels.keys():
            message = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        births, summary = channels[TOPICS["Birth"]], channels[SUMMARY_TOPIC]
        subscriptions = [
            {"id": 7, "channelId": births["id"]},
            {"id": 8, "channelId": summary["id"]},
        ]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
        received: list[dict] = []
        latest_summary: dict = {}
        index = 1
        while not received or latest_summary.get("births", [])[-1:] != [received[-1]["birth"]]:
            if not received:  # until the subscription is in place at the server
                bus.publish(_birth(bus.run, index))
                index += 1
            try:
                frame = await asyncio.wait_for(ws.recv(), 0.5)
            except TimeoutError:
                assert index < 60, "no birth came back"
                continue
            if isinstance(frame, str):
                continue
            opcode, subscription, _ = struct.unpack_from("<BIQ", frame)
            assert opcode == MESSAGE_DATA
            payload = json.loads(frame[13:])
            if subscription == 7:
                received.append(payload)
            else:
                assert subscription == 8
                latest_summary = payload
        return channels, received[0], received, latest_summary


def test_a_websocket_client_receives_the_births_as_json(
    coordinator: tuple[str, Bus], bridge: int
) -> None:
    _, bus = coordinator
    channels, first, received, summary = asyncio.run(_watch(bridge, bus))
    served = {topic: json_schema(kind) for kind, topic in TOPICS.items()}
    served[SUMMARY_TOPIC] = viewer_schema(RunSummary)
    for topic, channel in channels.items():  # the schemas the viewers' parser reads
        assert channel["encoding"] == "json" and channel["schemaEncoding"] == "jsonschema"
        schema = json.loads(channel["schema"])
        assert schema == served[topic], topic
        assert parse_json_schema(schema, channel["schemaName"])[channel["schemaName"]], topic
    assert first == json_form(_birth(bus.run, first["birth"]), base64_text)  # the birth's JSON
    assert len({b["birth"] for b in received}) == len(received)  # each birth once
    # the summary holds the queried birth 0 too, in birth order, with the best so far
    last = received[-1]["birth"]
    assert summary["run"] == bus.run and summary["births"][0] == 0
    assert summary["births"] == sorted(summary["births"]) and summary["births"][-1] == last
    fitness = summary["fitness"]
    assert summary["best"] == [max(fitness[: k + 1]) for k in range(len(fitness))]
    assert summary["recent"][0]["birth"] == last


def test_summary_slots_workers_and_marks_the_silent_ones_idle() -> None:
    bridge = Bridge("r", foxglove.Context())
    for node, at in (("t1", 0.0), ("t2", 1.0), ("t1", 2.0)):
        progress = TrainProgress(
            run="r", agent="a1", job="j", node=node, env_steps=1, total_steps=8, steps_per_s=100.0
        )
        bridge.apply(progress, at)
    bridge.apply(_birth("other", 3), 0.0)  # another run's birth is not this run's
    summary = bridge.summary(6.5)
    assert [(w.node, w.steps_per_s) for w in summary.workers] == [("t1", 100.0), ("t2", 0.0)]
    assert summary.births == []


def _resolve(datatypes: dict[str, list[dict]], root: str, path: str) -> dict:
    """The field a message path (``.a[:].b``) names, walked through the viewers' datatypes."""
    field: dict = {"type": root, "isComplex": True}
    for name, index in re.findall(r"\.(\w+)|(\[[^\]]*\])", path):
        if index:
            assert field.get("isArray"), f"{path}: {index} on a field that is not an array"
            field = {**field, "isArray": False}
        else:
            assert field.get("isComplex") and not field.get("isArray"), f"{path}: .{name}"
            field = next(f for f in datatypes[field["type"]] if f["name"] == name)
    return field


def test_the_layout_reads_only_what_the_bridge_serves() -> None:
    """Every message path of docs/foxglove-layout.json names a served topic and a field of it,
    resolved in the message definitions the viewers make of the served schema; plotted ones
    are numbers."""
    layout = json.loads(LAYOUT.read_text())
    schemas = {topic: (kind, json_schema(kind)) for kind, topic in TOPICS.items()}
    schemas[SUMMARY_TOPIC] = ("RunSummary", viewer_schema(RunSummary))
    plots = [c for panel, c in layout["configById"].items() if panel.startswith("Plot")]
    plotted = set(re.findall(r'"(/derl/[^"]*)"', json.dumps(plots)))
    paths = re.findall(r'"(/derl/[^"]*)"', json.dumps(layout))
    assert len(paths) >= 6 and len(plotted) >= 3
    for path in paths:
        topic, dot, rest = path.partition(".")
        assert topic in schemas, path
        kind, schema = schemas[topic]
        field = _resolve(parse_json_schema(schema, kind), kind, dot + rest)
        assert path not in plotted or field["type"] == "float64", path
    panels = set(layout["configById"])
    assert {panel.split("!")[0] for panel in panels} == {"Plot", "Table", "RawMessages"}
    assert panels == set(re.findall(r'"(\w+![\w-]+)"', json.dumps(layout["layout"])))
    for panel, config in layout["configById"].items():  # titles under the keys the apps read
        assert "title" not in config, panel
        if panel.startswith("Plot"):
            assert config["foxglovePanelTitle"] == config["lichtblickPanelTitle"] != "", panel
