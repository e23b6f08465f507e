"""The `derl` command line: argument parsing and printing only, one module per command group."""

import os

# MuJoCo picks its OpenGL backend when first imported: offscreen EGL unless the user chose one.
os.environ.setdefault("MUJOCO_GL", "egl")
