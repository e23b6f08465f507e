"""Trainer and evaluator nodes."""
