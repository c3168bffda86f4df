"""Shared test setup: headless GL for any MuJoCo rendering, quiet JAX on CPU."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("JAX_PLATFORMS", "cpu")
