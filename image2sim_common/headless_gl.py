"""Which OpenGL MuJoCo renders with on a machine without a display. Call before `mujoco` is imported."""

from __future__ import annotations

import os


def choose_headless_gl(*, even_with_display: bool = False) -> None:
    """Renders on the CPU with OSMesa where MuJoCo's default (GLFW) has no display to open, unless the user chose a
    backend (``MUJOCO_GL=egl`` for a GPU). ``even_with_display``: OSMesa also where a display exists (the command
    line, which renders off-screen only and must not depend on a desktop session)."""
    if "MUJOCO_GL" in os.environ or (os.environ.get("DISPLAY") and not even_with_display):
        return
    os.environ["MUJOCO_GL"] = "osmesa"
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
