"""The UNIMAL design space: genomes, mutations, validity, MJCF compilation and descriptors."""

from typing import TYPE_CHECKING

from derl.lazy import exports

if TYPE_CHECKING:  # the names for type checkers, which do not run `__getattr__`
    from derl.unimal.canonical import body_hash as body_hash
    from derl.unimal.canonical import canonical_form as canonical_form
    from derl.unimal.canonical import canonical_genome as canonical_genome
    from derl.unimal.descriptors import Descriptors as Descriptors
    from derl.unimal.descriptors import describe as describe
    from derl.unimal.descriptors import stability_ratio as stability_ratio
    from derl.unimal.genome import Genome as Genome
    from derl.unimal.genome import Joint as Joint
    from derl.unimal.genome import Limb as Limb
    from derl.unimal.mjcf import agent_spec as agent_spec
    from derl.unimal.mjcf import standalone_spec as standalone_spec
    from derl.unimal.mjcf import to_mjcf as to_mjcf
    from derl.unimal.mutations import OPERATORS as OPERATORS
    from derl.unimal.mutations import Mutation as Mutation
    from derl.unimal.mutations import MutationFailed as MutationFailed
    from derl.unimal.mutations import applicable as applicable
    from derl.unimal.mutations import mutate as mutate
    from derl.unimal.sampling import random_genome as random_genome
    from derl.unimal.sampling import sample_population as sample_population
    from derl.unimal.sampling import shape_key as shape_key
    from derl.unimal.validity import InvalidBody as InvalidBody
    from derl.unimal.validity import check_body as check_body

# imported on first use: a genome (`derl.unimal.genome`, what a message carries) needs no MuJoCo
__getattr__, __all__ = exports(
    __name__,
    {
        "canonical": ("body_hash", "canonical_form", "canonical_genome"),
        "descriptors": ("Descriptors", "describe", "stability_ratio"),
        "genome": ("Genome", "Joint", "Limb"),
        "mjcf": ("agent_spec", "standalone_spec", "to_mjcf"),
        "mutations": ("OPERATORS", "Mutation", "MutationFailed", "applicable", "mutate"),
        "sampling": ("random_genome", "sample_population", "shape_key"),
        "validity": ("InvalidBody", "check_body"),
    },
)
