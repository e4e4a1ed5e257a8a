"""march: model-assisted RL for perceptive humanoid control over sparse footholds (on mjlab)."""

__version__ = "0.1.0"
