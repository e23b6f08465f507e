"""The one dispatch convention (`derl.messages.dispatch`): handlers marked with their message
types, the most derived one run, used by the coordinator, the journal's fold, the monitor and the
Foxglove bridge."""

from __future__ import annotations

from derl.messages import MESSAGE_TYPES, Birth, ChildFailed, TrainJob
from derl.messages.dispatch import Handler, handles
from derl.messages.examples import examples
from derl.nodes.coordinator.node import Coordinator
from derl.nodes.coordinator.run.state import EvolutionState
from derl.nodes.journal.history import RunHistory
from derl.nodes.tools.foxglove import Bridge
from derl.nodes.tools.monitor import RunView


class Base(Handler):
    def __init__(self) -> None:
        self.seen: list[str] = []

    @handles(Birth, ChildFailed)
    def on_settled(self, msg: Birth | ChildFailed, tag: str) -> str:
        self.seen.append(f"base {msg.type} {tag}")
        return "base"


class Derived(Base):
    def on_settled(self, msg: Birth | ChildFailed, tag: str) -> str:
        super().on_settled(msg, tag)
        self.seen.append("derived")
        return "derived"


def test_the_most_derived_handler_runs_and_an_unhandled_type_gives_none() -> None:
    by_type = {m.type: m for m in examples("r")}
    handler = Derived()
    assert handler.dispatch(by_type["Birth"], "x") == "derived"
    assert handler.dispatch(by_type["ChildFailed"], "y") == "derived"
    assert handler.dispatch(by_type["TrainJob"], "z") is None
    assert handler.seen == ["base Birth x", "derived", "base ChildFailed y", "derived"]
    assert (
        Base()._handlers == Derived()._handlers == {Birth: "on_settled", ChildFailed: "on_settled"}
    )


def test_every_reader_of_messages_dispatches_by_the_one_convention() -> None:
    """The fold takes every fact of the journal; the coordinator's state adds the decisions it
    keeps; the coordinator takes what workers send; the monitor and the bridge what they show."""
    facts = {"TrainJob", "EvalJob", "FitnessReport", "Birth", "ChildFailed", "Quarantine",
             "Retrained", "Undo", "Dropped", "JobFailed", "JobLost", "EvalResult",
             "RunSettings"}  # fmt: skip
    assert {t.__name__ for t in RunHistory._handlers} == facts
    assert {t.__name__ for t in EvolutionState._handlers} == facts | {"Tournament", "Cancel"}
    assert {t.__name__ for t in Coordinator._handlers} == {
        "WorkerReady", "TrainProgress", "FitnessReport", "EvalResult", "JobFailed"}  # fmt: skip
    assert {t.__name__ for t in Bridge._handlers} == {"Birth", "ChildFailed", "TrainProgress"}
    assert {t.__name__ for t in RunView._handlers} >= {"RunStatus", "TrainJob", "Ack"}
    assert all(t.__name__ in MESSAGE_TYPES for t in RunView._handlers)
    assert TrainJob in RunView._handlers
