"""``python -m march.bench env|planner``: env and planner speed against bare mjlab, as JSON."""
