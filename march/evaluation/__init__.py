"""The evaluation protocol shared by every arm: the same courses, commands, terminations and
per-episode metrics (:mod:`.protocol`)."""
