"""Every metric of `derl.analysis` on a hand-built run whose answers are worked out by hand.

The tree (P = 3 founders, then 4 children, in birth order):

    a (10) ── d (350, grow_limb) ──┬── f (700)
                                   └── g (100)
    b (20)
    c (30) ── e (40)

The final population is the last 3 born (e, f, g): lineages a (f, g) and c (e) survive, b does
not. With the FT threshold 300, d (+340) and f (+350) are beneficial mutations, both in a's
lineage. The learning criterion is the 75th percentile of {10, 20, 30} = 25.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from body_variants import variants
from matplotlib.figure import Figure
from scipy import stats

from derl.analysis import (
    AnalysisConfig,
    Body,
    Evaluation,
    RunLog,
    analyse,
    plan,
    plots,
    rank_by_mean,
)
from derl.analysis.learning import (
    by_generation,
    cost_of_work,
    criterion,
    generations,
    learning_speed,
    steps_to_reach,
)
from derl.analysis.lineage import (
    Tree,
    beneficial,
    final_members,
    fitness_gain,
    lineages,
    muller,
    time_grid,
    window,
)
from derl.analysis.morphology import Morphology, column, over_time, sample
from derl.analysis.progress import describe
from derl.analysis.report import headline
from derl.analysis.selection import new_seeds, top_of_surviving_lineages
from derl.analysis.statistics import (
    BootstrapConfig,
    Clustered,
    Measure,
    censored_median,
    compare_medians,
    estimate,
    mann_whitney,
    pearson,
    spearman,
    stars,
)
from derl.analysis.tables import body_rows
from derl.analysis.testsuite import compare, results, summarize
from derl.unimal import Genome, body_hash

STEPS = (100, 200, 300)
# id, parent, fitness, curve returns, cost of work, mutation
TREE = (
    ("a", None, 10.0, (5.0, 8.0, 10.0), 4.0, None),
    ("b", None, 20.0, (10.0, 20.0, 20.0), 3.0, None),
    ("c", None, 30.0, (20.0, 26.0, 30.0), 2.0, None),
    ("d", "a", 350.0, (30.0, 300.0, 350.0), 1.0, "grow_limb"),
    ("e", "c", 40.0, (0.0, 0.0, 40.0), float("nan"), "gear"),
    ("f", "d", 700.0, (25.0, 500.0, 700.0), 0.5, "density"),
    ("g", "d", 100.0, (10.0, 24.9, 100.0), 1.5, "dof"),
)
ORDER = "abcdefg"


def make_run(genome: Genome | None = None, name: str = "r", world: str = "ft", evaluations=()):
    """The run of the module's docstring; given `genome`, each body a different variant of it."""
    genomes = variants(genome, len(TREE)) if genome is not None else [None] * len(TREE)
    bodies = tuple(
        Body(
            id=body,
            parent=parent,
            birth=k,
            fitness=fitness,
            curve_steps=STEPS,
            curve_returns=curve,
            cost_of_work=cost,
            energy=100.0,
            mass=10.0,
            mutation=mutation,
            genome=genomes[k],
        )
        for k, (body, parent, fitness, curve, cost, mutation) in enumerate(TREE)
    )
    return RunLog(
        name=name,
        world=world,
        bodies=bodies,
        evaluations=evaluations,
        train_steps=300,
        training_seed=1409,
    )


@pytest.fixture
def run() -> RunLog:
    return make_run()


@pytest.fixture
def tree(run: RunLog) -> Tree:
    return Tree.of(run)


def ids(indices) -> list[str]:
    return [ORDER[int(i)] for i in indices]


# --- records -----------------------------------------------------------------------------------


def test_records_must_form_a_tree_in_birth_order() -> None:
    with pytest.raises(ValueError, match="parent"):
        RunLog(name="x", world="ft", bodies=(Body(id="a", parent="z", birth=0, fitness=1),))
    with pytest.raises(ValueError, match="birth"):
        RunLog(name="x", world="ft", bodies=(Body(id="a", birth=1, fitness=1),))
    with pytest.raises(ValueError, match="curve"):
        Body(id="a", birth=0, fitness=1, curve_steps=(1, 2), curve_returns=(1.0,))


# --- the tree ----------------------------------------------------------------------------------


def test_founders_generations_and_descendants(run: RunLog, tree: Tree) -> None:
    assert run.population == 3
    assert ids(tree.founder) == list("abcacaa")
    assert tree.generation.tolist() == [0, 0, 0, 1, 1, 2, 2]
    assert dict(zip(ORDER, tree.descendants.tolist(), strict=True)) == dict(
        a=3, b=0, c=1, d=2, e=0, f=0, g=0
    )
    assert ids(tree.ancestry(5)) == ["a", "d", "f"]
    order = ids(tree.preorder())
    assert order == ["a", "d", "f", "g", "b", "c", "e"]


def test_population_windows_and_time_grid(run: RunLog) -> None:
    assert window(7, 3) == slice(4, 7)
    assert window(2, 3) == slice(0, 2)
    assert time_grid(run, 50).tolist() == [3, 4, 5, 6, 7]
    assert time_grid(run, 2).tolist() == [3, 7]


def test_beneficial_mutations_with_a_threshold(run: RunLog, tree: Tree) -> None:
    gain = fitness_gain(run, tree)
    assert np.isnan(gain[:3]).all()
    assert gain[3:].tolist() == [340.0, 10.0, 350.0, -250.0]
    assert ids(np.flatnonzero(beneficial(run, tree, 300))) == ["d", "f"]
    assert ids(np.flatnonzero(beneficial(run, tree, 345))) == ["f"]
    assert ids(np.flatnonzero(beneficial(run, tree, 340))) == ["d", "f"]  # ">= threshold"
    assert ids(np.flatnonzero(beneficial(run, tree, -1000))) == ["d", "e", "f", "g"]


def test_lineages(run: RunLog, tree: Tree) -> None:
    assert final_members(run, tree) == {0: 2, 2: 1}
    rows = {row.founder: row for row in lineages(run, tree, 300)}
    assert [row.founder for row in lineages(run, tree, 300)] == ["a", "c", "b"]
    a, b, c = rows["a"], rows["b"], rows["c"]
    assert (a.founder_rank, b.founder_rank, c.founder_rank) == (3, 2, 1)
    assert (a.bodies, b.bodies, c.bodies) == (4, 1, 2)
    assert (a.final_members, a.final_abundance) == (2, pytest.approx(2 / 3))
    assert (c.final_members, c.final_abundance) == (1, pytest.approx(1 / 3))
    assert (a.surviving, b.surviving, c.surviving) == (True, False, True)
    assert (a.beneficial_mutations, b.beneficial_mutations, c.beneficial_mutations) == (2, 0, 0)
    assert (a.best_agent, a.best_fitness, a.max_generation) == ("f", 700.0, 2)


def test_muller_abundances(run: RunLog, tree: Tree) -> None:
    times = time_grid(run, 50)
    m = muller(run, tree, lineages(run, tree, 300), times, count=10, star_descendants=1)
    assert m.founders == ["a", "c"]
    expected = np.array([[1, 1], [1, 1], [1, 2], [2, 1], [2, 1]]) / 3
    np.testing.assert_allclose(m.abundance, expected)
    assert (m.abundance.sum(axis=1) <= 1 + 1e-12).all()
    assert m.fitness[3, 0] == pytest.approx((350 + 700) / 2)  # t=6: d and f
    assert m.fitness[4, 1] == 40.0
    assert m.stars == [(3, 0, "d")]  # grow_limb with 2 > 1 descendants
    only_one = muller(run, tree, lineages(run, tree, 300), times, count=1, star_descendants=20)
    assert only_one.founders == ["a"] and only_one.stars == []


# --- learning speed and the Baldwin effect -----------------------------------------------------


def test_steps_to_the_criterion(run: RunLog) -> None:
    level = criterion(run, 75)
    assert level == 25.0
    speed = learning_speed(run, level)
    # a and b never reach 25: censored at their budget (the curve's last step), not dropped
    np.testing.assert_array_equal(speed.values, [300, 300, 200, 100, 300, 100, 300])
    assert speed.censored.tolist() == [True, True, False, False, False, False, False]
    assert steps_to_reach(run.bodies[6], 24.9) == 200  # reaching the level exactly counts
    assert math.isnan(steps_to_reach(run.bodies[0], 25.0))
    no_curve = run.bodies[0].model_copy(update={"curve_steps": (), "curve_returns": ()})
    missing = learning_speed(run.model_copy(update={"bodies": (no_curve, *run.bodies[1:])}), 25)
    assert math.isnan(missing.values[0]) and not missing.censored[0]  # unknown, not censored


def test_by_generation_follows_the_top_agents_ancestors(run: RunLog, tree: Tree) -> None:
    config = BootstrapConfig()
    top = np.array([5, 6])  # f, g: both children of d, grandchildren of a
    layers = generations(tree, top, run.original)
    assert [ids(layer) for layer in layers] == [["a"], ["d"], ["f", "g"]]  # a and d once each
    mean = lambda m: estimate(m.values, config)  # noqa: E731
    points = by_generation([(layers, Measure.exact(run.fitness))], mean)
    assert [p.x for p in points] == [0, 1, 2]
    assert [(p.n, p.value) for p in points] == [(1, 10.0), (1, 350.0), (2, 400.0)]
    assert points[0].low is None  # a single value has no CI
    median = lambda m: censored_median(m.values, m.censored, 0.95)  # noqa: E731
    speed = by_generation([(layers, learning_speed(run, 25.0))], median)
    # generation 0 is a: it never reaches the criterion, counted (it was left out); f and g
    # reach it after 100 and 300 steps
    assert [(p.n, p.censored, p.value) for p in speed] == [(1, 1, None), (1, 0, 100.0),
                                                           (2, 0, 200.0)]  # fmt: skip
    two = by_generation([(layers, Measure.exact(run.fitness))] * 2, mean)  # two runs pooled
    assert [p.n for p in two] == [2, 2, 4]


def test_a_shared_ancestor_counts_once_per_generation(
    quadruped: Genome, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The top 3 agents f, d and g all descend from a, and f and g from d: by generation the
    ancestors are a, then d, then f and g, each once (a and d were counted 3 times each); fig. 2a
    (right) writes each generation's n at its point."""
    config = AnalysisConfig(top=3, time_points=5, stability_sample=1)
    analysis = analyse([make_run(quadruped)], config)
    (result,) = analysis.runs
    assert ids(result.top) == ["f", "d", "g"]
    fitness = result.series["fitness_by_generation"]
    assert [(p.n, p.value) for p in fitness] == [(1, 10.0), (1, 350.0), (2, 400.0)]  # n: 3, 3, 2
    speed = result.series["steps_to_criterion"]
    assert [(p.n, p.censored) for p in speed] == [(1, 1), (1, 0), (2, 0)]  # was (3, 3), (3, 0)
    drawn: list[Figure] = []
    monkeypatch.setattr(plots, "_save", lambda figure, path: drawn.append(figure) or path)
    plots.fitness(Path("unused.png"), analysis)
    assert [t.get_text() for t in drawn[0].axes[1].texts] == ["1", "1", "2"]


def test_a_censored_median_is_kaplan_meiers() -> None:
    """Six bodies reach the criterion at 1..6 steps, three never do within 10: the survival
    curve is 8/9, 7/9, ..., 3/9, so the median is 5 (4/9 <= 1/2); its CI is where scipy's
    band crosses 1/2, and the upper limit is unbounded (the band stays above it)."""
    values = [1, 2, 3, 4, 5, 6, 10, 10, 10]
    censored = [False] * 6 + [True] * 3
    result = censored_median(values, censored, 0.95)
    assert (result.n, result.censored, result.value) == (9, 3, 5.0)
    band = stats.ecdf(stats.CensoredData(uncensored=values[:6], right=values[6:])).sf
    low = band.confidence_interval(0.95, method="log-log").low
    assert result.low == low.quantiles[np.flatnonzero(low.probabilities <= 0.5)[0]]
    assert result.high is None
    dropping = np.median(values[:6])  # what leaving them out said: 3.5, a faster median
    assert dropping < result.value
    plain = censored_median([4.0, 1.0, 3.0, 2.0], [False] * 4, 0.95)
    assert plain.value == 2.5 == np.median([1, 2, 3, 4])  # no censoring: the plain median
    assert censored_median([1, 2, 9, 9], [0, 0, 1, 1], 0.95).value is None  # half censored
    beyond = censored_median([1.0, np.inf, 2.0], [False, True, False], 0.95)
    assert (beyond.value, beyond.censored) == (2.0, 1)  # +inf: beyond every measured value
    assert censored_median([np.nan, np.inf], [False, True], 0.95).model_dump() == dict(
        n=1, value=None, low=None, high=None, censored=1
    )


@pytest.mark.filterwarnings("ignore:The confidence interval is undefined")
def test_a_censored_value_before_every_measured_one_keeps_the_interval_honest() -> None:
    """One body censored at 0.5, nine measured at 1..9: the median is 5. Before the first
    measured value the survival curve is 1 and scipy's log-log band undefined (NaN); read as 0,
    it put both limits at 0.5 (CI [0.5, 0.5]). The band is 1 there: the limits are where it
    crosses 1/2 (1 and 8); where it is undefined because the curve is 0, it never crosses (a
    limit found only there is unbounded)."""
    values, censored = [0.5, *range(1, 10)], [True] + [False] * 9
    result = censored_median(values, censored, 0.95)
    assert (result.n, result.censored, result.value) == (10, 1, 5.0)
    assert (result.low, result.high) == (1.0, 8.0)  # was (0.5, 0.5)
    band = stats.ecdf(stats.CensoredData(uncensored=values[1:], right=values[:1])).sf
    band = band.confidence_interval(0.95, method="log-log")
    for limit, found in ((band.low, result.low), (band.high, result.high)):
        assert found == limit.quantiles[np.flatnonzero(limit.probabilities <= 0.5)[0]]
    few = censored_median([0.5, 1, 2, 3, 4], [True] + [False] * 4, 0.95)
    assert (few.value, few.low, few.high) == (2.5, 1.0, None)  # was (2.5, 0.5, 0.5)


def test_cost_of_work_of_no_positive_reward_is_censored(run: RunLog) -> None:
    poor = run.bodies[1].model_copy(update={"fitness": -5.0, "cost_of_work": float("nan")})
    cost = cost_of_work(run.model_copy(update={"bodies": (run.bodies[0], poor, *run.bodies[2:])}))
    assert cost.censored.tolist() == [False, True, False, False, False, False, False]
    assert cost.values[1] == np.inf
    assert np.isnan(cost.values[4]) and not cost.censored[4]  # e: positive reward, unknown cost


# --- statistics --------------------------------------------------------------------------------


def test_bootstrap_ci_is_scipys() -> None:
    data = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 9.0])
    config = BootstrapConfig(n_resamples=5000, seed=3)
    for statistic, function in (("mean", np.mean), ("median", np.median)):
        result = estimate(data, config, statistic)
        direct = stats.bootstrap(
            (data,), function, n_resamples=5000, method="BCa", rng=np.random.default_rng(3)
        ).confidence_interval
        assert result.value == function(data)
        assert (result.low, result.high) == pytest.approx((direct.low, direct.high))
        assert result.low < result.value < result.high
    assert estimate([np.nan, 2.0], config).model_dump() == dict(
        n=1, value=2.0, low=None, high=None, censored=0
    )
    assert estimate([], config).n == 0


def test_the_difference_of_two_medians_is_bootstrapped_reproducibly() -> None:
    """With each value its own cluster, the cluster bootstrap is scipy's two-sample one."""
    rng = np.random.default_rng(0)
    first, last = rng.normal(10, 3, 40), rng.normal(14, 3, 40)
    config = BootstrapConfig(n_resamples=1000, seed=5)
    alone = Clustered(first, np.arange(40)), Clustered(last, np.arange(40, 80))
    a, b, result = compare_medians(*alone, config)
    direct = stats.bootstrap(
        (first, last),
        lambda a, b, axis=-1: np.median(b, axis=axis) - np.median(a, axis=axis),
        n_resamples=1000,
        method="BCa",
        rng=np.random.default_rng(5),
    ).confidence_interval
    assert (a.value, b.value) == (np.median(first), np.median(last)) and (a.n, b.n) == (40, 40)
    assert result.value == pytest.approx(np.median(last) - np.median(first))
    assert (result.low, result.high) == pytest.approx((direct.low, direct.high))
    assert result.low < result.value < result.high and result.n == 80
    assert compare_medians(*alone, config)[2] == result  # seeded: the same again
    assert compare_medians(Clustered([1.0], [0]), Clustered([2.0], [1]), config)[2].low is None


def test_pearson_on_known_relations() -> None:
    x = np.arange(10.0)
    exact = pearson(x, 3 * x + 2)
    assert exact.r == pytest.approx(1.0) and exact.p < 1e-10
    assert pearson(x, -x).r == pytest.approx(-1.0)
    known = pearson([1, 2, 3, 4, np.nan], [1, 3, 2, 4, 7])  # r = 0.8, t = 1.886 on 2 df
    assert (known.n, known.excluded) == (4, 1)
    assert known.r == pytest.approx(0.8) and known.p == pytest.approx(0.2)
    assert pearson([1, 2], [2, 3]).r is None
    assert pearson([1, 1, 1], [1, 2, 3]).note == "a constant variable"
    censored = pearson([1, 2, 3, 4, np.inf], [1, 3, 2, 4, 7])  # a censored x: left out
    assert (censored.n, censored.excluded, censored.r) == (4, 1, pytest.approx(0.8))


def test_spearman_counts_censored_values_as_the_largest() -> None:
    x = [1.0, 2.0, 3.0, 4.0, np.inf, np.inf]
    y = [2.0, 1.0, 4.0, 3.0, 9.0, 8.0]
    result = spearman(x, y)
    expected = stats.spearmanr([1, 2, 3, 4, 5.5, 5.5], [2, 1, 4, 3, 6, 5])  # ties beyond all
    assert (result.n, result.censored, result.excluded) == (6, 2, 0)
    assert result.r == pytest.approx(expected.statistic)
    assert result.p == pytest.approx(expected.pvalue)
    assert spearman([1, 2, np.nan, 4], [1, 2, 3, 4]).excluded == 1


def test_mann_whitney_on_known_samples() -> None:
    separated = mann_whitney([1, 2, 3], [4, 5, 6])
    assert (separated.u, separated.p) == (0.0, pytest.approx(0.1))  # exact: 2 / C(6, 3)
    assert separated.stars == "ns"
    far = mann_whitney(np.arange(20.0), np.arange(20.0) + 100)
    assert far.p < 1e-4 and far.stars == "****"
    assert mann_whitney([], [1.0]).p is None
    assert [stars(p) for p in (0.2, 0.04, 0.009, 0.0009, 0.00009)] == [
        "ns",
        "*",
        "**",
        "***",
        "****",
    ]


# --- morphology over time ----------------------------------------------------------------------


def test_population_means_over_time() -> None:
    values = np.array([1, 2, 3, 4, 5, 6, 7], dtype=float)
    points = over_time([(values, 3)], np.array([3, 7]), BootstrapConfig())
    assert [(p.x, p.n, p.value) for p in points] == [(3, 3, 2.0), (7, 3, 6.0)]
    stable = [True, False, None, True]
    rows = [
        Morphology(length=1, width=1, height=1, dof=2, limbs=2, mass=1, passively_stable=s)
        for s in stable
    ]
    flags = column(rows, "passively_stable")
    np.testing.assert_array_equal(flags, [1.0, 0.0, np.nan, 1.0])
    (share,) = over_time([(flags, 4)], np.array([4]), BootstrapConfig())
    assert (share.n, share.value) == (3, pytest.approx(2 / 3))


def test_stability_sample_spreads_over_birth_order() -> None:
    assert sample(10, 4).tolist() == [0, 3, 6, 9]
    assert sample(3, 5).tolist() == [0, 1, 2]


# --- the test-task suite -----------------------------------------------------------------------


def test_suite_medians_and_world_comparison() -> None:
    def evaluations(rewards):
        return tuple(
            Evaluation(agent=f"x{k}", task="patrol", seed=k, reward=r, cost_of_work=1.0 / r)
            for k, r in enumerate(rewards)
        )

    ft = make_run(name="one", world="ft", evaluations=evaluations([1.0, 2.0, 3.0]))
    vt = make_run(name="two", world="vt", evaluations=evaluations([4.0, 5.0, 6.0]))
    rows, repeated = results([ft, vt])
    assert len(rows) == 6 and {r.world for r in rows} == {"ft", "vt"} and repeated == 0
    summary = {s.world: s for s in summarize(rows, BootstrapConfig())}
    assert summary["ft"].reward.value == 2.0 and summary["vt"].reward.value == 5.0
    assert summary["vt"].cost_of_work.value == pytest.approx(1 / 5)
    (reward, cost) = compare(rows)
    assert (reward.task, reward.metric, reward.world_a, reward.world_b) == (
        "patrol",
        "reward",
        "ft",
        "vt",
    )
    assert (reward.test.u, reward.test.p) == (0.0, pytest.approx(0.1))
    assert (cost.metric, cost.test.u) == ("cost_of_work", 9.0)


# --- selection (appendix D) --------------------------------------------------------------------


def test_top_bodies_of_surviving_lineages(run: RunLog, tree: Tree) -> None:
    assert ids(top_of_surviving_lineages(run, tree, 2)) == ["f", "d", "e", "c"]
    assert ids(top_of_surviving_lineages(run, tree, 1)) == ["f", "e"]


def test_retraining_plan(quadruped: Genome) -> None:
    result = plan([make_run(quadruped)], per_lineage=2, seeds=3, seed=7)
    assert len(result.seeds) == 3 and 1409 not in result.seeds
    assert len(set(result.seeds)) == 3
    assert len(result.jobs) == 4 * 3
    assert [j.agent for j in result.jobs[::3]] == ["f", "d", "e", "c"]
    assert {j.lineage for j in result.jobs if j.agent in "fd"} == {"a"}
    assert {(j.task, j.steps) for j in result.jobs} == {("ft", 300)}
    assert {j.seed for j in result.jobs} == set(result.seeds)
    assert result.jobs[0].genome == variants(quadruped, 7)[ORDER.index("f")]
    assert new_seeds(2, {5}, 0) == new_seeds(2, {5}, 0)


# --- everything together -----------------------------------------------------------------------


def test_analyse_a_run(quadruped: Genome) -> None:
    config = AnalysisConfig(time_points=5)
    analysis = analyse([make_run(quadruped)], config)
    (result,) = analysis.runs
    s = result.summary
    assert (s.bodies, s.distinct_bodies, s.repeats, s.population, s.generations) == (7, 7, 0, 3, 3)
    assert [row.repeat_of for row in body_rows(result)] == [None] * 7  # bodies.csv
    assert (s.top_of_population, s.top_agents) == (2, 2)
    assert (s.beneficial_threshold, s.beneficial_mutations, s.surviving_lineages) == (300, 2, 2)
    assert (s.criterion_reached, s.criterion_censored, s.no_positive_reward) == (5, 2, 0)
    assert s.stability_simulated == 7
    assert s.gain_p75 == pytest.approx(np.percentile([340, 10, 350], 75))
    top = result.series["fitness_top"]
    assert [p.x for p in top] == [3, 4, 5, 6, 7]
    assert [p.value for p in top] == [25.0, 190.0, 195.0, 525.0, 400.0]  # top 2 of the window
    assert ids(result.top) == ["f", "d"]
    (world,) = analysis.worlds  # fig. 5d's lineage is now chosen among the world's top agents
    assert world.illustrative[0] is result
    assert ORDER[world.illustrative[1]] == "f"  # the top agent with the most generations
    # the ancestors' median cost of work: a (4), then d (1), then f (0.5)
    assert [p.value for p in result.series["cost_of_work"]] == [4.0, 1.0, 0.5]
    assert [p.value for p in result.series["dof"]] == [quadruped.dof] * 5
    assert result.morphology[0].passively_stable is not None
    q = s.quarters  # 7 births: quarters of 1, a (10) and g (100)
    assert (q.births, q.first.value, q.last.value, q.difference.value) == (1, 10.0, 100.0, 90.0)


def with_repeat(run: RunLog, genome: Genome | None = None) -> RunLog:
    """`run` and one more birth: h, a second child of d with f's body (a repeat of f: its
    result), born last."""
    f = run.bodies[ORDER.index("f")]
    h = f.model_copy(update={"id": "h", "birth": len(run.bodies), "repeat_of": "f"})
    return run.model_copy(update={"bodies": (*run.bodies, h)})


def test_a_repeat_is_its_original(quadruped: Genome) -> None:
    run = with_repeat(make_run(quadruped))
    assert run.original.tolist() == [0, 1, 2, 3, 4, 5, 6, 5]
    assert run.distinct.tolist() == [True] * 7 + [False]
    untold = run.bodies[-1].model_copy(update={"repeat_of": None})  # the same body, trained
    missed = run.model_copy(update={"bodies": (*run.bodies[:-1], untold)})
    assert missed.original.tolist() == run.original.tolist()  # by body_hash
    told = with_repeat(make_run())  # no genomes: by the journal's repeat_of
    assert told.original.tolist() == run.original.tolist()


def test_the_selection_counts_a_body_once(quadruped: Genome) -> None:
    """h repeats f: a lineage's top 2 are f and d, not f twice; a body of an earlier run of the
    world is not selected again, nor retrained with the same seeds."""
    run = with_repeat(make_run(quadruped))
    tree = Tree.of(run)
    assert ids(top_of_surviving_lineages(run, tree, 2)) == ["f", "d"]  # was f, h
    one, two = with_repeat(make_run(quadruped, "one")), with_repeat(make_run(quadruped, "two"))
    chosen = plan([one, two], per_lineage=2, seeds=3)
    assert [(j.run, j.agent) for j in chosen.jobs[::3]] == [("one", "f"), ("one", "d")]
    assert len({(body_hash(j.genome), j.seed) for j in chosen.jobs}) == len(chosen.jobs)


def test_retrained_bodies_are_ranked_once_and_only_when_complete() -> None:
    results = [("x", 1, 10.0), ("x", 2, 30.0), ("y", 1, 25.0), ("y", 2, 25.0),
               ("z", 1, 90.0), ("y", 1, 25.0)]  # fmt: skip
    ranking = rank_by_mean(results)  # z: 1 of 2 seeds, its 90 would rank first
    assert ranking.ranked == [("y", 25.0), ("x", 20.0)]
    assert (ranking.partial, ranking.results, ranking.duplicates) == (["z"], 5, 1)


def test_a_repeat_counts_once_where_bodies_are_counted(quadruped: Genome) -> None:
    """The population holds both f and h (fig. 2a's top of the population); the top agents,
    the beneficial mutations (h is f's mutation from d again), fig. 6 and the pictures hold f
    once."""
    config = AnalysisConfig(top=3, time_points=50, stability_sample=1)
    analysis = analyse([with_repeat(make_run(quadruped))], config)
    (result,) = analysis.runs
    s = result.summary
    assert (s.bodies, s.distinct_bodies, s.repeats) == (8, 7, 1)
    assert ids(result.top) == ["f", "d", "g"]  # was f, h, d
    assert s.beneficial_mutations == 2  # was 3: d and f, and f again
    assert s.gain_p75 == pytest.approx(np.percentile([340, 10, 350], 75))
    assert result.series["fitness_top"][-1].value == 500.0  # the population f, g, h: all of it
    every = {(r.y, r.generation): r for r in analysis.correlations if r.agents == "all"}
    assert every[("fitness", None)].spearman.n == 6  # 8 births, 7 bodies, e without a cost
    assert every[("fitness", 2)].spearman.n == 2  # f and g (h is f)
    rows = body_rows(result)
    assert (rows[-1].same_body_as, rows[-1].counted) == ("f", False)
    q = result.summary.quarters  # the last 2 births: g and h (f's body): one lineage, a's
    assert (q.last.n, q.last.value, q.last_lineages, q.difference.low) == (2, 400.0, 1, None)


def quarters_run(genome: Genome, late: str) -> RunLog:
    """16 births, quarters of 4: founders a, b, c, d (10, 20, 30, 40); their children; then a4
    (100), a5 (a4's body again: a repeat), and x and y (200, 210), children of `late`."""
    rows = (
        ("a", None, 10.0), ("b", None, 20.0), ("c", None, 30.0), ("d", None, 40.0),
        ("a1", "a", 50.0), ("b1", "b", 60.0), ("a2", "a1", 70.0), ("b2", "b1", 80.0),
        ("a3", "a2", 90.0), ("b3", "b2", 95.0), ("c1", "c", 35.0), ("d1", "d", 45.0),
        ("a4", "a3", 100.0), ("a5", "a3", 100.0), ("x", late, 200.0), ("y", late, 210.0),
    )  # fmt: skip
    genomes = variants(genome, len(rows))
    genomes[13] = genomes[12]
    return RunLog(
        name="q",
        world="ft",
        bodies=tuple(
            Body(
                id=body,
                parent=parent,
                birth=k,
                fitness=fitness,
                genome=genomes[k],
                repeat_of="a4" if body == "a5" else None,
            )
            for k, (body, parent, fitness) in enumerate(rows)
        ),
    )


def test_the_quarters_compare_distinct_bodies_resampling_lineages(quadruped: Genome) -> None:
    """The last quarter is a4, its repeat a5, x and y: 3 bodies (100, 200, 210), median 200 (not
    150, a4 twice); x and y are b's lineage, a4 a's. Lineages are resampled, not bodies, each
    bringing its bodies of both quarters: the first quarter's a and b come with the last's
    bodies of their lineage. A last quarter of one lineage has no interval."""
    config = AnalysisConfig(stability_sample=1, time_points=5, gaits=0,
                            bootstrap=BootstrapConfig(method="percentile"))  # fmt: skip
    analysis = analyse([quarters_run(quadruped, "b3")], config)
    q = analysis.runs[0].summary.quarters
    assert (q.first.value, q.last.value, q.difference.value) == (25.0, 200.0, 175.0)
    assert (q.births, q.first.n, q.last.n, q.first_lineages, q.last_lineages) == (4, 4, 3, 4, 2)
    # resampled lineages in the last quarter: a twice (100), a and b (200), b twice (205)
    assert (q.last.low, q.last.high) == (100.0, 205.0)
    # a, b resampled with c, d: a twice and c twice (20) ... b twice and d twice (30)
    assert (q.first.low, q.first.high) == (20.0, 30.0)
    # a twice: the first quarter 20 or 25, the last 100; b twice: 25 or 30 and 205
    assert (q.difference.low, q.difference.high) == (75.0, 180.0)
    assert describe("q", q, config.bootstrap) == (
        "q: median fitness of the first 4 births 25, of the last 4 200, each body once (4 and 3 "
        "distinct bodies, of 4 and 2 lineages); difference 175, 95% CI [75, 180] (bootstrap of "
        "lineages, percentile, 2000 resamples, seed 0)"
    )
    one = analyse([quarters_run(quadruped, "a3")], config).runs[0].summary.quarters
    assert (one.last.value, one.last_lineages, one.difference.value) == (200.0, 1, 175.0)
    assert one.difference.low is one.last.low is None  # a's lineage alone: nothing to resample
    assert "difference 175, no interval (too few lineages to resample)" in describe(
        "q", one, config.bootstrap
    )


def test_runs_of_a_world_are_compared_as_replicates_paired_over_seeds(quadruped: Genome) -> None:
    """Three runs of FT (seeds), each with a difference between its quarters (175 scaled by 1.0,
    1.1, 1.2: 175, 192.5, 210): their mean, 192.5, with the t interval over the 3 runs and the
    paired t test; a world of one run has none."""
    config = AnalysisConfig(stability_sample=1, time_points=5, gaits=0,
                            bootstrap=BootstrapConfig(method="percentile"))  # fmt: skip
    base = quarters_run(quadruped, "b3")
    runs = [
        base.model_copy(update={"name": f"s{k}", "bodies": tuple(
            b.model_copy(update={"fitness": b.fitness * (1 + k / 10)}) for b in base.bodies)})
        for k in range(3)
    ]  # fmt: skip
    analysis = analyse(runs, config)
    (world,) = analysis.worlds
    replicated = world.summary.replicates
    assert replicated is not None and replicated.runs == ["s0", "s1", "s2"]
    assert replicated.differences == pytest.approx([175.0, 192.5, 210.0])
    half = stats.t.ppf(0.975, 2) * 17.5 / np.sqrt(3)  # sd 17.5 over 3 runs
    mean = replicated.mean
    assert (mean.n, mean.value) == (3, pytest.approx(192.5))
    assert (mean.low, mean.high) == (pytest.approx(192.5 - half), pytest.approx(192.5 + half))
    assert replicated.p_value == pytest.approx(2 * stats.t.sf(192.5 / (17.5 / np.sqrt(3)), 2))
    line = next(line for line in headline(analysis) if "runs as replicates" in line)
    assert line.startswith("FT, 3 runs as replicates: the last quarter's median fitness minus")
    assert "s0 +175, s1 +192.5, s2 +210; mean +192.5, 95% CI [+149" in line
    assert analyse(runs[:1], config).worlds[0].summary.replicates is None


def test_fig6_correlations_pool_each_world_and_each_generation(quadruped: Genome) -> None:
    config = AnalysisConfig(top=3, stability_sample=1)
    one, two = make_run(quadruped, "one"), make_run(quadruped, "two")
    others = variants(quadruped, 14)[7:]  # two's bodies: other bodies than one's
    two = two.model_copy(update={"bodies": tuple(
        b.model_copy(update={"genome": g}) for b, g in zip(two.bodies, others, strict=True)
    )})  # fmt: skip
    analysis = analyse([one, two], config)
    rows = {(r.world, r.agents, r.y, r.generation): r for r in analysis.correlations}
    top = rows[("ft", "top", "fitness", None)]  # f, d, g of both runs
    expected = stats.pearsonr([0.5, 1, 1.5] * 2, [700, 350, 100] * 2)
    assert top.pearson.n == 6 and top.pearson.r == pytest.approx(expected.statistic)
    assert top.pearson.p == pytest.approx(expected.pvalue)
    every = rows[("ft", "all", "steps_to_criterion", None)]
    assert (every.pearson.n, every.pearson.excluded) == (8, 6)  # e: no cost; a, b: never reach
    assert (every.spearman.n, every.spearman.excluded, every.spearman.censored) == (12, 2, 4)
    founders = rows[("ft", "all", "fitness", 0)]  # generation 0: a, b, c of both runs
    expected = stats.pearsonr([4, 3, 2] * 2, [10, 20, 30] * 2)
    assert founders.pearson.r == pytest.approx(expected.statistic)
    assert {g for (_, agents, _, g) in rows if agents == "all"} == {None, 0, 1, 2}
    same = analyse([one, make_run(quadruped, "three")], config)  # the same bodies again
    again = {(r.agents, r.y, r.generation): r for r in same.correlations}
    assert again[("all", "fitness", None)].spearman.n == 6  # each body once (e: no cost)
    assert same.worlds[0].summary.shared_bodies == 7


def test_thresholds_come_from_the_world() -> None:
    config = AnalysisConfig()
    assert (config.threshold("ft"), config.threshold("vt"), config.threshold("mvt")) == (
        300,
        100,
        100,
    )
    with pytest.raises(ValueError, match="no beneficial-mutation threshold"):
        config.threshold("moon")
    assert AnalysisConfig(beneficial={"ft": 5}).threshold("ft") == 5
    assert [config.top_of(n) for n in (3, 8, 16, 576, 4000)] == [2, 2, 4, 100, 100]
