"""``python -m march.robot``: the exported student on a Unitree G1 over DDS (or on a MuJoCo G1
that speaks the robot's DDS topics on the loopback interface). Jobs: ``policy`` (the robot-side
loop), ``sim`` (the MuJoCo robot), ``selftest`` (both, checked against in-process sim-to-sim).
See docs/deploying.md."""
