"""Evaluation jobs and their results, the same in every rule set: a run's test stage and a study.

The state plans the evaluations (an agent in a task with a seed and a budget: `EvalKey`) and
hands out the next one waiting; an `EvalJob` carries the agent's body and its learning
configuration. A result is taken once, from the job issued to its sender for that evaluation,
and only with a finite score; one for an evaluation done already is acknowledged again. An
evaluation whose jobs failed `max_attempts` times is given up (the state counts the failures).
"""

from __future__ import annotations

import logging
import math

from derl.messages import EvalJob, EvalResult
from derl.nodes.coordinator.jobs import Job, JobBook
from derl.nodes.coordinator.ledger import Ledger
from derl.plugins import Plugin

log = logging.getLogger("derl.coordinator")


def evaluation_job(
    state: JobBook, run: str, node: str, lease_s: float, plugins: tuple[Plugin, ...] = ()
) -> EvalJob | None:
    """The next waiting evaluation as a job for `node`, if there is one (naming `plugins`, the
    run's)."""
    key = state.next_evaluation()
    if key is None:
        return None
    agent, task, _, _ = key
    genome, ppo = state.evaluation_order(key)
    return EvalJob(
        run=run,
        job=f"e{len(state.issued) + 1}-{agent}"[:128],
        agent=agent,
        node=node,
        genome=genome,
        task=task,
        ppo=ppo,
        lease_s=lease_s,
        plugins=plugins,
    )


def on_evaluation(ledger: Ledger, result: EvalResult) -> None:
    """Take `result` (journaled, acknowledged), acknowledge it again, or reject it."""
    state = ledger.state
    order = state.orders.get(result.job)
    key = (result.agent, result.task, result.seed, result.steps)
    if not state.issued_to(result.job, result.node, result.agent):
        ledger.never_issued(result, result.agent, f" in {result.task}")  # whatever its state
    elif key in state.evaluations:
        ledger.answer_again(result, result.agent)
    elif (
        not isinstance(order, EvalJob) or (order.agent, order.task, order.seed, order.steps) != key
    ):
        ledger.never_issued(result, result.agent, f" in {result.task}")
    elif not math.isfinite(result.reward):
        ledger.reject(result, result.agent, "a non-finite score")
    else:
        ledger.commit(result, publish=False)
        ledger.ack(result, result.agent)


def log_given_up(state: JobBook, job: Job, max_attempts: int) -> None:
    """Say so if `job`'s failure gave its evaluation up."""
    if job.evaluation is not None and (job.agent, *job.evaluation) in state.eval_given_up:
        log.error("evaluation of %s in %s given up after %d failures", job.agent,
                  job.evaluation[0], max_attempts)  # fmt: skip
