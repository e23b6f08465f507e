"""The smallest custom monitor: print each body's fitness as the run reports it.

    python examples/fitness_monitor.py RUN [ENDPOINT]    # ENDPOINT default tcp/127.0.0.1:7447

It joins the bus as a peer (multicast off, like every derl node), subscribes to
``derl/RUN/fitness/*`` through a RingChannel (when this script falls behind, the oldest
reports are dropped: a monitor must never slow a trainer), decodes each payload with
`messages.decode` and prints one line per child (trainers re-send a report until the
coordinator acknowledges it). Ctrl-C stops it.
"""

import sys
import time

import zenoh

from messages import DecodeError, FitnessReport, KeySpace, decode
from nodes.runtime.bus import ZenohOptions, open_session

run, endpoint = sys.argv[1], (sys.argv[2:] or ["tcp/127.0.0.1:7447"])[0]
seen: set[str] = set()
with open_session(ZenohOptions(connect=(endpoint,))) as session:
    key = KeySpace(run).all("fitness")  # derl/RUN/fitness/*
    reports = session.declare_subscriber(key, zenoh.handlers.RingChannel(64))
    try:
        while True:
            sample = reports.try_recv()
            if sample is None:
                time.sleep(0.05)
                continue
            try:
                report = decode(sample.payload.to_bytes(), FitnessReport)
            except DecodeError as error:
                print(f"skipped {sample.key_expr}: {error}", file=sys.stderr)
                continue
            if report.child not in seen:
                seen.add(report.child)
                print(f"{report.child} fitness {report.fitness:.2f} ({report.node})", flush=True)
    except KeyboardInterrupt:
        pass
