"""DERL's science, importable without the bus: bodies, worlds, learning, evolution, analysis."""
