"""The UNIMAL design space: genomes, mutations, validity, MJCF compilation and descriptors."""

from derl.unimal.canonical import body_hash, canonical_form, canonical_genome
from derl.unimal.descriptors import Descriptors, describe, stability_ratio
from derl.unimal.genome import Genome, Joint, Limb
from derl.unimal.mjcf import agent_spec, standalone_spec, to_mjcf
from derl.unimal.mutations import OPERATORS, Mutation, MutationFailed, applicable, mutate
from derl.unimal.sampling import random_genome, sample_population, shape_key
from derl.unimal.validity import InvalidBody, check_body

__all__ = [
    "OPERATORS",
    "Descriptors",
    "Genome",
    "InvalidBody",
    "Joint",
    "Limb",
    "Mutation",
    "MutationFailed",
    "agent_spec",
    "applicable",
    "body_hash",
    "canonical_form",
    "canonical_genome",
    "check_body",
    "describe",
    "mutate",
    "random_genome",
    "sample_population",
    "shape_key",
    "stability_ratio",
    "standalone_spec",
    "to_mjcf",
]
