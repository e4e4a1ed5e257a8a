"""``python -m march.audit``: checks of the reward and the reference before a costly run."""
