"""A study's state: the job book (`jobs`) with appendix D's two stages as its evaluations.

First every planned retraining (a selected body in its own world with a new seed: `retrainings`),
then, once each has its result or was given up, the test stage: per world, the `top` of the
`keep` best bodies by mean retrained fitness (`kept`), on every test task with every test seed at
every budget. The test stage is derived from the journal's results, so a restarted coordinator
plans it again, identically. A study decides no children: every journaled message is applied.
"""

from __future__ import annotations

from derl.analysis.selection import RetrainJob, RetrainPlan, kept_bodies
from derl.analysis.study import StudyConfig
from derl.nodes.coordinator.jobs import JobBook
from derl.nodes.coordinator.study.files import selected_bodies, study_agent
from derl.nodes.errors import Refused
from derl.nodes.journal.history import EvalKey
from derl.rl import PPOConfig
from derl.unimal import Genome


class StudyState(JobBook):
    """The jobs in flight and appendix D's two stages as evaluations (see the module)."""

    def __init__(self, config: StudyConfig, plan: RetrainPlan) -> None:
        super().__init__(config.max_attempts)
        self.config = config
        self.selected = selected_bodies(plan)  # agent -> its body
        self.retrainings: list[EvalKey] = [self._retraining(job) for job in plan.jobs]
        self.worlds = list(dict.fromkeys(job.task for job in plan.jobs))
        self.tested: dict[str, list[tuple[str, float]]] = {}  # world -> (agent, mean), planned

    def _retraining(self, job: RetrainJob) -> EvalKey:
        """The evaluation that retrains `job`'s body: with the study's budget, else its run's."""
        agent = study_agent(job)
        if len(agent) > 128:
            raise Refused(f"study agent name {agent!r} is longer than 128 characters")
        steps = self.config.retrain_steps or job.steps
        if steps is None:
            raise Refused(f"{job.run} records no lifetime budget: set retrain_steps")
        return (agent, job.task, job.seed, steps)

    def _plan_evaluations(self) -> None:
        if not self.planned:
            for key in self.retrainings:
                self._plan(key)
        if self.tested or not self.evaluations_over(self.retrainings):
            return
        config = self.config
        for world, kept in self.kept().items():
            self.tested[world] = kept[: config.top]
            for agent, _ in self.tested[world]:
                for task in config.test_tasks:
                    for steps in config.budgets:
                        for seed in range(config.test_seeds):
                            self._plan((agent, task, seed, steps))

    def kept(self) -> dict[str, list[tuple[str, float]]]:
        """Per world, the `keep` best retrained bodies by mean fitness over their new seeds (each
        body once, ranked only with every seed's result: `derl.analysis.selection.kept_bodies`)."""
        results = [
            (key[0], key[2], self.evaluations[key].reward)
            for key in self.retrainings
            if key in self.evaluations
        ]
        return kept_bodies(self.selected, results, self.config.keep)

    def evaluation_order(self, key: EvalKey) -> tuple[Genome, PPOConfig]:
        agent, task, seed, steps = key
        return self.selected[agent].genome, self.config.job_ppo(task, steps, seed)

    @property
    def eval_target(self) -> int:
        """The retrainings, and the tests of at most `top` bodies per world."""
        config = self.config
        per_body = len(config.test_tasks) * len(config.budgets) * config.test_seeds
        bodies = {w: sum(j.task == w for j in self.selected.values()) for w in self.worlds}
        tested = sum(min(config.top, n) for n in bodies.values())
        if self.tested:
            tested = sum(len(agents) for agents in self.tested.values())
        return len(self.retrainings) + tested * per_body

    @property
    def finished(self) -> bool:
        self._plan_evaluations()
        return bool(self.tested) and self.evaluations_over(self.planned)
