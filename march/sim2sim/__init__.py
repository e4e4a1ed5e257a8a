"""``python -m march.sim2sim``: the exported student in plain MuJoCo + onnxruntime, nothing of the
training stack (no torch, warp, mjlab or Hydra): :mod:`.deploy_bundle` reads the bundle,
:mod:`.depth_camera` renders the depth image, :mod:`.runner` runs the control loop (with the
training's latencies), :mod:`.guard` flags inputs outside training, :mod:`.command_line` is the
command.
"""

import os
import sys

# As mjlab (and so march.play) does: offscreen video through EGL on Linux (Mesa's software EGL
# needs no GPU). mujoco reads MUJOCO_GL once, when it is imported: set here, before any module of
# this package imports it.
if sys.platform.startswith("linux"):
    os.environ.setdefault("MUJOCO_GL", "egl")
