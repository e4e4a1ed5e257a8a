"""`python -m march.audit`: the entry point of the audit tool (reference, rewards, envelope)."""

import os

# MuJoCo picks its rendering backend when first imported (the reference job films the G1).
os.environ.setdefault("MUJOCO_GL", "egl")

from march.audit.audit_command import main  # noqa: E402

main()
