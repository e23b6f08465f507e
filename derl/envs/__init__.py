"""Environments: terrain, tasks and batched simulation of UNIMAL bodies."""
