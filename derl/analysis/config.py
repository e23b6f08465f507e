"""What a report computes, as one pydantic model: thresholds, sizes and resampling settings.

Defaults are the paper's where it gives one: beneficial mutations of at least 300 (FT) and 100
(VT, MVT) fitness, the 75th percentile of the initial population as the learning criterion, the
top 100 agents, the top 10 lineages in the Muller diagram, stars on topology changes with more
than 20 descendants, 95% bootstrapped CIs.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from derl.analysis.statistics import BootstrapConfig

PAPER_TOP = 100
BENEFICIAL = {"ft": 300.0, "vt": 100.0, "mvt": 100.0}


class AnalysisConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    beneficial: dict[str, float] = Field(
        default_factory=lambda: dict(BENEFICIAL),
        description="least fitness gain over the parent that makes a mutation beneficial, by world",
    )
    top: int | None = Field(
        None, ge=1, description="the top agents (None: 100, or a quarter of a smaller population)"
    )
    criterion_percentile: float = Field(
        75.0, gt=0, lt=100, description="of the initial population's fitness: learning criterion"
    )
    time_points: int = Field(50, ge=2, description="places on the birth-order axis")
    muller_lineages: int = Field(10, ge=1)
    star_descendants: int = Field(
        20, ge=0, description="topology changes with more descendants get a star (Muller)"
    )
    stability_sample: int = Field(
        500, ge=1, description="bodies whose passive stability is simulated (all if fewer)"
    )
    processes: int = Field(1, ge=1, description="processes for the stability simulations")
    pictures: int = Field(8, ge=0, description="best bodies drawn")
    gaits: int = Field(3, ge=0, description="best bodies filmed walking, a GIF each (0: none)")
    bootstrap: BootstrapConfig = BootstrapConfig()

    def threshold(self, world: str) -> float:
        """The beneficial-mutation threshold of `world`."""
        if world not in self.beneficial:
            raise ValueError(
                f"no beneficial-mutation threshold for world {world!r}; give one "
                f"(known: {', '.join(f'{w}={v:g}' for w, v in self.beneficial.items())})"
            )
        return self.beneficial[world]

    def top_of(self, size: int) -> int:
        """How many agents are 'the top' among `size`: the paper's 100, fewer in small runs."""
        if self.top is not None:
            return min(self.top, size)
        return min(PAPER_TOP, max(2, size // 4), size)
