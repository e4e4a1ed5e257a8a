"""march: model-assisted RL for perceptive humanoid control over sparse footholds (on mjlab)."""

import logging

__version__ = "0.1.0"

# PyOpenGL (imported with mjlab's viewers) logs "No OpenGL_accelerate module loaded" at INFO, and
# Hydra's logging prints INFO on stdout: a one-line error came second, after a line not ours.
# Set before anything imports it (Hydra's config keeps the levels of loggers it does not name).
logging.getLogger("OpenGL").setLevel(logging.WARNING)
