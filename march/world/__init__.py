"""The world: stepping-stone courses (geometry, difficulty, the hardware course) and the foothold
table the planner and the rewards read. Plain numpy/torch, no simulator import."""
