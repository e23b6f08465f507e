"""The smallest custom monitor: print each birth of a run, with only `zenoh` and `msgpack`.

    python examples/fitness_monitor.py RUN [ENDPOINT]    # ENDPOINT default tcp/127.0.0.1:7447

`derl run` names the run after its run directory (``runs/smoke`` -> ``smoke``) and listens on
tcp/127.0.0.1:7447. This script joins the bus as a Zenoh peer that connects to that endpoint
(multicast scouting off, like every derl node), first asks the coordinator for the births so far (a
query on ``derl/RUN/births/*``), then subscribes to the birth stream ``derl/RUN/births/*`` through
a RingChannel (when it falls behind, the oldest samples are dropped: a monitor must never slow the
run). It also reads the coordinator's status (``derl/RUN/status``, once a second): when that counts
more births and failed children than it has printed (a birth journaled just before a coordinator
crash and never published, or dropped by the RingChannel), it asks again, at each status until the
answer fills the gap or holds all the coordinator remembers. Each payload is a msgpack
map with ``type`` "Birth" (agent, parent, fitness, cost_of_work, birth, generation, node, mutation,
...) or "ChildFailed" (agent, attempts, error); docs/protocol.md lists every field. Births are
journaled before they are published, so these are exactly the run's births; a birth heard twice
(query and stream) is printed once. Ctrl-C stops it.
"""

import json
import sys
import time

import msgpack
import zenoh

if not 2 <= len(sys.argv) <= 3 or sys.argv[1].startswith("-"):
    sys.exit("usage: python examples/fitness_monitor.py RUN [ENDPOINT]")
run, endpoint = sys.argv[1], (sys.argv[2:] or ["tcp/127.0.0.1:7447"])[0]
config = zenoh.Config()
config.insert_json5("mode", json.dumps("peer"))
config.insert_json5("connect/endpoints", json.dumps([endpoint]))
config.insert_json5("scouting/multicast/enabled", "false")
seen: set[str] = set()


def show(sample: zenoh.Sample) -> None:
    try:
        event = msgpack.unpackb(sample.payload.to_bytes())
        kind, agent = event["type"], event["agent"]
    except (ValueError, TypeError, KeyError, msgpack.UnpackException) as error:
        print(f"skipped {sample.key_expr}: {error!r}", file=sys.stderr, flush=True)
        return
    if agent in seen:
        return
    seen.add(agent)
    if kind == "Birth":
        print(f"{agent} fitness {event['fitness']:.2f} ({event['node']})", flush=True)
    elif kind == "ChildFailed":
        print(f"{agent} failed after {event['attempts']} attempts: {event['error']}", flush=True)


REMEMBERED = 1000  # the births a coordinator answers a query with (derl: REMEMBERED_BIRTHS)


def ask(session: zenoh.Session, key: str) -> int:
    """Show the births the coordinator remembers; how many it answered with."""
    answered = 0
    for reply in session.get(key, timeout=2.0):
        if reply.ok is not None:
            answered += 1
            show(reply.ok)
    return answered


with zenoh.open(config) as session:
    key = f"derl/{run}/births/*"
    births = session.declare_subscriber(key, zenoh.handlers.RingChannel(256))
    status = session.declare_subscriber(f"derl/{run}/status", zenoh.handlers.RingChannel(1))
    ask(session, key)
    gap = 0  # what asking cannot fill (a late monitor of a run beyond the 1,000 remembered)
    try:
        while True:
            sample, news = births.try_recv(), status.try_recv()
            if sample is not None:
                show(sample)
            if news is not None:
                counts = msgpack.unpackb(news.payload.to_bytes())
                settled = counts["born"] + counts["failed"]
                # one went by unheard: ask (again at the next status while the answer falls
                # short, e.g. a coordinator just restarted whose queryable is not reached yet)
                if settled - len(seen) > gap and ask(session, key) >= REMEMBERED:
                    gap = settled - len(seen)
            if sample is None and news is None:
                time.sleep(0.05)
    except KeyboardInterrupt:
        pass
