"""The agents shipped in agents/ (the README's clips): each loads as a `derl train` folder and,
replayed with its deterministic policy, does what its clip shows: in FT and VT it walks forward,
in MVT it walks towards the box."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from derl.replay import Trained, play

AGENTS = sorted(path for path in (Path(__file__).parents[1] / "agents").iterdir() if path.is_dir())
SPEED = 0.5
"""m/s a walking agent trained to the paper's budget keeps at least over its first 250 control
steps (measured: the FT agent about 1 m/s from a standing start, 1.4 m/s over whole episodes)."""
MANIPULATION = 400.0
"""The least manipulation score (reach + push) of the MVT agent's first whole episode: the reach
term pays 100 a metre the body comes closer to the box (15-25 m ahead at the start), so this is 4
m closer (measured: 494-1,048 over its first 4 episodes, 1,045 in the first; it comes 5-10 m
closer to the box and reaches it in none of them within 20 s)."""


def test_agents_are_shipped() -> None:
    assert {path.name for path in AGENTS} >= {"ft", "vt", "mvt"}


@pytest.mark.parametrize("folder", AGENTS, ids=lambda path: path.name)
def test_a_shipped_agent_does_what_its_clip_shows(folder: Path) -> None:
    trained = Trained.load(folder)
    result = json.loads((folder / "result.json").read_text())
    assert result["env_steps"] >= 4_990_000  # the paper's budget, in whole rollouts
    assert trained.task == folder.name
    if trained.task == "mvt":
        (episode,) = play(trained, episodes=1)  # a whole episode: the box is far
        assert episode.total > MANIPULATION, episode
        return
    (episode,) = play(trained, episodes=1, episode_steps=250)
    metres = episode.total / 50  # forward reward: 50 per metre (velocity x 20 ms steps)
    assert not episode.fell and metres > SPEED * 250 * 0.02
