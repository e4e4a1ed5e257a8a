"""Stage 2's mathematics: the control Lyapunov function of the tracking error (CARE solution,
V, dV/dt history) that the CLF rewards are built on (:mod:`.lyapunov`). Plain torch, no simulator
import; the reward terms that read it are in :mod:`march.env.rewards`."""
