"""Stage 1 of the paper, the model-based reference: the HLIP model (:mod:`.hlip`), the footstep
planner over the stones (:mod:`.planner`) and the swing-foot / CoM / pelvis reference trajectory
of a step (:mod:`.trajectory`). Plain torch, no simulator import."""
