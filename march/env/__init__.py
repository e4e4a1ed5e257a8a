"""The bridge to mjlab, and the only code of march that imports it: the env config built from
march's typed config (:mod:`.build`), the stepping-stone terrain, the reference command term,
observations, rewards, terminations, domain randomization and the depth camera."""
