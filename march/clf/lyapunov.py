"""Control-Lyapunov-function (CLF) math for the CLF-RL rewards (paper eq. clf_rewards).

Plain torch + scipy: no simulator import. The env's reward terms feed this module the output
errors; everything here is batched over envs (leading dimension ``E``).

Model
- Each tracked output ``i`` (29 by default, see ``CLF_OUTPUT_NAMES``) is treated as a double
  integrator in its error ``eta_i = y_sim,i - y_ref,i``: state ``x_i = [eta_i, etadot_i]``,
  ``A = [[0, 1], [0, 0]]``, ``B = [0, 1]^T``, weights ``Q_i = diag(q_pos, q_vel)`` and scalar
  ``R_i = r``. ``P_i`` solves the continuous-time algebraic Riccati equation (CARE)
  ``A^T P + P A - P B R^-1 B^T P + Q = 0`` (``scipy.linalg.solve_continuous_are``), once, at
  construction. The full ``P`` is block-diagonal in the interleaved state
  ``x = [eta_1, etadot_1, eta_2, etadot_2, ...]``.
- Angular outputs must already be wrapped (or be quaternion-log errors) when they reach
  ``ClfModel.value``; this module never wraps.

Formulas (V as in the paper, with the 1/2; Vmax/Vdmax are the first author's normalisers)
- ``V = 1/2 x^T P x``                                                         (E,)
- ``Vmax  = lambda_max(P) eta_max^2``
- ``Vdmax = 2 ||P||_2 eta_max etadot_max + alpha lambda_max(P) eta_max^2``
  (``||P||_2`` is the spectral norm; for the symmetric positive definite P it equals
  ``lambda_max(P)``; both are kept separate to mirror the author's formula.)
- ``r_clf  = exp(-min(V, Vmax) / Vmax)``                  in ``[e^-1, 1]``, 1 at V = 0
- ``r_dclf = -max((dV/dt + alpha V) / Vdmax, 0)``         ``<= 0``, 0 while V decays at rate
  ``>= alpha`` (``dV/dt <= -alpha V``)

Sign convention (one, everywhere): ``dclf_reward`` already returns a value ``<= 0`` (the
paper's ``r_dclf``), so its weight in the reward config is POSITIVE (author's magnitude: 1;
``r_clf`` weight +10). The author's code computes the positive violation ``clip(., 0, 1)`` with
weight -1 instead; that is the same term with both signs flipped — never combine a negative
value with a negative weight. ``ClfCfg.dclf_clip`` optionally bounds the penalty at
``-dclf_clip`` (the author clips at 1; the paper does not clip, so the default is ``None``).

dV/dt
``backward_difference`` is the three-point backward difference
``(3 V_t - 4 V_{t-1} + V_{t-2}) / (2 dt)`` (second-order accurate, exact on quadratics in t),
evaluated at the control rate (``dt = step_dt``, 0.02 s at 50 Hz). ``VHistory`` keeps the last
two V per env and is reset-safe: after ``reset(env_ids)`` (episode reset, or a reference switch
at touchdown — the new reference makes V discontinuous, so differencing across the switch would
produce a spurious spike) an env has no history, and the derivative falls back to
- no previous sample: ``dV/dt = 0`` and ``valid = False``;
- one previous sample: the first-order backward difference ``(V_t - V_{t-1}) / dt``;
- two previous samples: the three-point backward difference.
``ClfModel.dclf_reward(V, Vdot, valid)`` returns exactly 0 where ``valid`` is False (no
derivative, no penalty) instead of the ``-alpha V / Vdmax`` that ``Vdot = 0`` would give.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.linalg import solve_continuous_are

# Upper-body joints tracked as outputs (Unitree G1 29-dof names, the author's order).
UPPER_BODY_JOINTS: tuple[str, ...] = (
    "waist_yaw_joint",
    "waist_pitch_joint",
    "waist_roll_joint",
    "left_shoulder_pitch_joint",
    "right_shoulder_pitch_joint",
    "left_shoulder_roll_joint",
    "right_shoulder_roll_joint",
    "left_shoulder_yaw_joint",
    "right_shoulder_yaw_joint",
    "left_elbow_joint",
    "right_elbow_joint",
    "left_wrist_roll_joint",
    "right_wrist_roll_joint",
    "left_wrist_pitch_joint",
    "right_wrist_pitch_joint",
    "left_wrist_yaw_joint",
    "right_wrist_yaw_joint",
)

_A = np.array([[0.0, 1.0], [0.0, 0.0]])
_B = np.array([[0.0], [1.0]])


@dataclass
class ClfOutputCfg:
    """CARE weights of one tracked output (a double integrator in its error)."""

    name: str
    """Output name, e.g. ``"com_x"``, ``"swing_z"`` or a joint name."""
    q_pos: float
    """Q weight on the position error eta [1/unit^2; unit = m for positions, rad for angles]."""
    q_vel: float
    """Q weight on the velocity error etadot [s^2/unit^2]."""
    r: float
    """R weight on the virtual input (the error's acceleration) [s^4/unit^2]; > 0."""


def default_clf_outputs() -> list[ClfOutputCfg]:
    """The paper's 29 outputs with the first author's public Q/R weights.

    Order (= column order of ``eta``): CoM x/y/z (stance-foot frame), pelvis roll/pitch/yaw,
    swing foot position x/y/z, swing foot orientation roll/pitch/yaw, 17 upper-body joints.
    The spec quotes swing_z 3500/100, swing_x 1500/125, com_x 25/200 and R 0.01-0.1; the rest
    are the same public author values (facts, not tuned here): R 0.1 for CoM and waist,
    0.05 pelvis and swing position, 0.02 swing orientation, 0.01 arm joints.
    """
    w = [
        ("com_x", 25.0, 200.0, 0.1),
        ("com_y", 300.0, 50.0, 0.1),
        ("com_z", 400.0, 10.0, 0.1),
        ("pelvis_roll", 420.0, 20.0, 0.05),
        ("pelvis_pitch", 200.0, 10.0, 0.05),
        ("pelvis_yaw", 300.0, 10.0, 0.05),
        ("swing_x", 1500.0, 125.0, 0.05),
        ("swing_y", 1700.0, 125.0, 0.05),
        ("swing_z", 3500.0, 100.0, 0.05),
        ("swing_roll", 30.0, 1.0, 0.02),
        ("swing_pitch", 10.0, 1.0, 0.02),
        ("swing_yaw", 400.0, 10.0, 0.02),
    ]
    upper = {
        "waist": (500.0, 10.0, 0.1),
        "shoulder_pitch": (40.0, 1.0, 0.01),
        "shoulder_roll": (100.0, 1.0, 0.01),
        "shoulder_yaw": (50.0, 1.0, 0.01),
        "elbow": (30.0, 1.0, 0.01),
        "wrist": (20.0, 1.0, 0.01),
    }
    for j in UPPER_BODY_JOINTS:
        key = next(k for k in upper if k in j)
        w.append((j, *upper[key]))
    return [ClfOutputCfg(n, qp, qv, r) for n, qp, qv, r in w]


CLF_OUTPUT_NAMES: tuple[str, ...] = tuple(o.name for o in default_clf_outputs())


@dataclass
class ClfCfg:
    """CLF reward configuration (paper eq. clf_rewards; author's normalisers)."""

    outputs: list[ClfOutputCfg] = field(default_factory=default_clf_outputs)
    """Tracked outputs, in the column order of ``eta``/``etadot``; 29 by default."""
    eta_max: float = 0.2
    """Error scale for the normalisers Vmax and Vdmax [m or rad, mixed units]."""
    etadot_max: float = 0.3
    """Error-rate scale for Vdmax [m/s or rad/s]."""
    alpha: float = 0.5
    """Required exponential decay rate of V in the dclf term [1/s]."""
    dclf_clip: float | None = None
    """If set, r_dclf is clipped below at ``-dclf_clip`` (author: 1.0). None: paper, unclipped."""

    @property
    def output_names(self) -> list[str]:
        return [o.name for o in self.outputs]


def solve_output_care(q_pos: float, q_vel: float, r: float) -> np.ndarray:
    """(2, 2) CARE solution P_i of one double-integrator output, float64."""
    if not (q_pos > 0 and q_vel >= 0 and r > 0):
        raise ValueError(f"need q_pos > 0, q_vel >= 0, r > 0; got {q_pos}, {q_vel}, {r}")
    p = solve_continuous_are(_A, _B, np.diag([q_pos, q_vel]), np.array([[r]]))
    return 0.5 * (p + p.T)


class ClfModel:
    """V, its normalisers and the two CLF reward terms; P computed once from a ``ClfCfg``."""

    def __init__(
        self,
        cfg: ClfCfg | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.cfg = cfg if cfg is not None else ClfCfg()
        outs = list(self.cfg.outputs)
        if not outs:
            raise ValueError("ClfCfg.outputs is empty")
        self.names: list[str] = [o.name for o in outs]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"duplicate output names in {self.names}")
        self.num_outputs = len(outs)
        blocks = np.stack([solve_output_care(o.q_pos, o.q_vel, o.r) for o in outs])  # (n,2,2)
        self.P_blocks_np: np.ndarray = blocks
        """(n, 2, 2) float64 per-output CARE solutions."""
        n = self.num_outputs
        p_full = np.zeros((2 * n, 2 * n))
        for i in range(n):
            p_full[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = blocks[i]
        self.P_np: np.ndarray = p_full
        """(2n, 2n) float64 block-diagonal P in the interleaved state [eta_1, etadot_1, ...]."""
        self.lambda_max: float = float(np.linalg.eigvalsh(p_full)[-1])
        """Largest eigenvalue of P."""
        self.p_norm: float = float(np.linalg.norm(p_full, 2))
        """Spectral norm ||P||_2 (= lambda_max for symmetric positive definite P)."""
        c = self.cfg
        self.alpha = float(c.alpha)
        self.v_max: float = self.lambda_max * c.eta_max**2
        """Vmax = lambda_max(P) eta_max^2 (author)."""
        self.vdot_max: float = (
            2.0 * self.p_norm * c.eta_max * c.etadot_max + c.alpha * self.lambda_max * c.eta_max**2
        )
        """Vdmax = 2 ||P|| eta_max etadot_max + alpha lambda_max(P) eta_max^2 (author)."""
        self.dtype = dtype
        self._set_tensors(torch.device(device))

    def _set_tensors(self, device: torch.device) -> None:
        self.device = device
        self.P = torch.as_tensor(self.P_np, dtype=self.dtype, device=device)
        b = torch.as_tensor(self.P_blocks_np, dtype=self.dtype, device=device)
        self._p11, self._p12, self._p22 = b[:, 0, 0], b[:, 0, 1], b[:, 1, 1]
        self._half_p = torch.as_tensor(0.5 * self.P_np, dtype=self.dtype, device=device)

    def to(self, device: torch.device | str) -> ClfModel:
        """Move the tensors to ``device`` (in place); returns self."""
        self._set_tensors(torch.device(device))
        return self

    def index(self, name: str) -> int:
        """Column of output ``name`` in eta."""
        return self.names.index(name)

    def state(self, eta: torch.Tensor, etadot: torch.Tensor) -> torch.Tensor:
        """(E, 2n) interleaved state x = [eta_1, etadot_1, ...] (the ordering of ``P``)."""
        return torch.stack([eta, etadot], dim=-1).flatten(-2)

    def _check(self, eta: torch.Tensor, etadot: torch.Tensor) -> None:
        if eta.shape != etadot.shape or eta.shape[-1] != self.num_outputs:
            raise ValueError(
                f"eta {tuple(eta.shape)} and etadot {tuple(etadot.shape)} must both be "
                f"(..., {self.num_outputs})"
            )

    def value(self, eta: torch.Tensor, etadot: torch.Tensor) -> torch.Tensor:
        """V = 1/2 x^T P x, shape (E,), from eta and etadot, each (E, n)."""
        self._check(eta, etadot)
        q = self._p11 * eta * eta + 2.0 * self._p12 * eta * etadot + self._p22 * etadot * etadot
        return 0.5 * q.sum(-1)

    def value_of_outputs(
        self,
        y: torch.Tensor,
        ydot: torch.Tensor,
        y_ref: torch.Tensor,
        ydot_ref: torch.Tensor,
        angles: torch.Tensor,
    ) -> torch.Tensor:
        """V (E,) of the outputs ``y`` and rates ``ydot`` against their references, each
        (E, n): eta = y - y_ref with the ``angles`` (n,) bool columns wrapped to [-pi, pi)
        (``march.reference.trajectory.tracking_error``), etadot = ydot - ydot_ref, and
        V = x^T (P / 2) x on the interleaved state as one product with the block-diagonal P:
        :meth:`value` in 9 ops instead of ~20 (equal within float32 rounding)."""
        return self.products_of_outputs(y, ydot, y_ref, ydot_ref, angles).sum(-1)

    def products_of_outputs(
        self,
        y: torch.Tensor,
        ydot: torch.Tensor,
        y_ref: torch.Tensor,
        ydot_ref: torch.Tensor,
        angles: torch.Tensor,
    ) -> torch.Tensor:
        """The interleaved products ``(x @ P/2) * x`` (E, 2n) whose sum is V
        (:meth:`value_of_outputs`); pairs of columns are each output's term of V
        (:func:`march.clf.diagnostics.output_terms`)."""
        diff = y - y_ref
        eta = torch.where(angles, torch.remainder(diff + math.pi, 2.0 * math.pi) - math.pi, diff)
        x = torch.stack([eta, ydot - ydot_ref], dim=-1).flatten(-2)
        return (x @ self._half_p) * x

    def value_rate(
        self, eta: torch.Tensor, etadot: torch.Tensor, etaddot: torch.Tensor
    ) -> torch.Tensor:
        """Exact dV/dt = x^T P xdot with xdot = [etadot, etaddot] (E,); for checks and tests."""
        self._check(eta, etadot)
        self._check(etadot, etaddot)
        q = (
            self._p11 * eta * etadot
            + self._p12 * (etadot * etadot + eta * etaddot)
            + self._p22 * etadot * etaddot
        )
        return q.sum(-1)

    def clf_reward(self, v: torch.Tensor) -> torch.Tensor:
        """r_clf = exp(-min(V, Vmax)/Vmax), in [e^-1, 1] (3 ops: the sign and 1/Vmax folded)."""
        return torch.exp(torch.clamp(v, max=self.v_max) * (-1.0 / self.v_max))

    def dclf_reward(
        self, v: torch.Tensor, vdot: torch.Tensor, valid: torch.Tensor | None = None
    ) -> torch.Tensor:
        """r_dclf = -max((Vdot + alpha V)/Vdmax, 0) <= 0; 0 where ``valid`` is False.

        Weight it POSITIVELY in the reward config (the value is already a penalty).
        """
        # -max(x, 0) = min(-x, 0), the sign and 1/Vdmax folded into one product and the clip
        # into the same clamp: 3 ops (+ the validity where), not 5 (+ 2)
        r = torch.add(vdot, v, alpha=self.alpha).mul_(-1.0 / self.vdot_max)
        clip = self.cfg.dclf_clip
        r = r.clamp_(max=0.0) if clip is None else r.clamp_(min=-float(clip), max=0.0)
        if valid is not None:
            r = torch.where(valid, r, 0.0)
        return r


def backward_difference(
    v_t: torch.Tensor, v_t1: torch.Tensor, v_t2: torch.Tensor, dt: float
) -> torch.Tensor:
    """Three-point backward difference (3 V_t - 4 V_{t-1} + V_{t-2}) / (2 dt).

    ``v_t1`` is V one step ago, ``v_t2`` two steps ago; exact when V is quadratic in t.
    """
    return (3.0 * v_t - 4.0 * v_t1 + v_t2) / (2.0 * dt)


class VHistory:
    """The last two V per env, giving a reset-safe backward-difference dV/dt.

    Call ``update(v)`` once per control step with the current V (after any ``reset`` of that
    step). ``reset(env_ids)`` forgets the history of those envs: call it on episode reset and
    when the reference switches (touchdown), so V is never differenced across a discontinuity.
    See the module docstring for the fallback order.
    """

    def __init__(
        self,
        num_envs: int,
        dt: float,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        if dt <= 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        self.dt = float(dt)
        self.v1 = torch.zeros(num_envs, dtype=dtype, device=device)
        """V one step ago."""
        self.v2 = torch.zeros(num_envs, dtype=dtype, device=device)
        """V two steps ago."""
        self.count = torch.zeros(num_envs, dtype=torch.long, device=device)
        """Number of stored past samples per env, 0..2."""
        d = self.dt
        self._weights = torch.tensor(
            [[0.0, 0.0, 0.0], [1.0 / d, -1.0 / d, 0.0], [1.5 / d, -2.0 / d, 0.5 / d]],
            dtype=dtype,
            device=device,
        )
        """(count, [V_t, V_t-1, V_t-2]) the backward difference's weights for each history
        length (0: none, 1: first order, 2: three-point)."""

    def reset(self, env_ids: torch.Tensor | Sequence[int] | slice | None = None) -> None:
        """Forget the history of ``env_ids`` (all envs if None)."""
        ids = slice(None) if env_ids is None else env_ids
        self.count[ids] = 0
        self.v1[ids] = 0.0
        self.v2[ids] = 0.0

    def forget(self, mask: torch.Tensor) -> None:
        """Forget the history where ``mask`` (E,) bool is True (``reset`` without indices, so
        without a host sync)."""
        self.count.masked_fill_(mask, 0)
        self.v1.masked_fill_(mask, 0.0)
        self.v2.masked_fill_(mask, 0.0)

    def update(self, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Push the current V (E,); return (dV/dt (E,), valid (E,) bool).

        valid is False where no previous sample exists (dV/dt is then 0).
        """
        v = v.detach().to(self.v1.dtype)
        # One weighted sum for the three cases (the weights by history length: ~8 ops, not
        # ~16; equal to backward_difference / the first-order difference within rounding).
        history = torch.stack([v, self.v1, self.v2], dim=-1)
        valid = self.count >= 1
        vdot = (history * self._weights[self.count]).sum(-1)
        vdot = torch.where(valid, vdot, 0.0)  # exactly 0 without history, even for V = inf
        self.v2 = self.v1
        self.v1 = v.clone()
        self.count = (self.count + 1).clamp_(max=2)
        return vdot, valid
