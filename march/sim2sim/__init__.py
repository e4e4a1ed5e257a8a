"""``python -m march.sim2sim``: the exported student in plain MuJoCo + onnxruntime, nothing of the
training stack (no torch, warp, mjlab or Hydra)."""
