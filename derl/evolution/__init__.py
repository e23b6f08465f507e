"""Evolution: run profiles and aging tournament selection, independent of any transport."""

from derl.evolution.config import PROFILES, EvolutionConfig, load_profile
from derl.evolution.evolution import Child, Evolution, breed
from derl.evolution.fingerprint import child_order, fingerprint
from derl.evolution.member import Member

__all__ = [
    "PROFILES",
    "Child",
    "Evolution",
    "EvolutionConfig",
    "Member",
    "breed",
    "child_order",
    "fingerprint",
    "load_profile",
]
