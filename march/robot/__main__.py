"""`python -m march.robot`: the entry point of the deploy tool (policy, sim, selftest, supervisor, camera)."""

from march.robot.robot_command import main

main()
