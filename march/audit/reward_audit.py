"""``python -m march.audit rewards``: does an arm's reward rank tracking above standing?

In the arm's own training env (``make_env(cfg, "teacher")``: its reward terms, terminations,
curriculum and domain randomisation), each canonical behaviour is rolled for ``HORIZON_STEPS``
control steps from the same seeded start (``reseed_env`` + ``torch.manual_seed`` + a full reset:
the same courses, commands and randomisation for every behaviour):

- ``zero``: action 0, i.e. the PD targets at the default pose (standing);
- ``random``: actions drawn as PPO's initial policy draws them: N(0, std_j^2) around the zero
  action with std_j the initial std of joint j's group (``teacher.init_std`` x
  ``teacher.init_std_<legs|waist|arms>``; 1.0 everywhere is the paper's), seeded; and, beside
  it, the same with the upper body's (waist and arms) std at each of ``UPPER_STD_OPTIONS``
  and the legs' kept: how much of the initial policy's V and saturation is the upper body's
  (issue 56);
- ``checkpoint``: a teacher checkpoint's deterministic policy (``teacher_ckpt=``), if given;
- ``reference``: the kinematic G1 PLACED on the planner's reference by whole-body IK every step
  (:class:`march.audit.kinematic_reference.KinematicReference`), where the arm has the
  reference. The pose is written into the simulator, not reached by torques: it cannot fall
  and the holonomic terms are paid by construction. Its V is the floor that perfect kinematic
  tracking reaches; it says what the reward would pay for tracking, not that tracking is
  physically achievable.

Each env's rollout counts up to the end of its first episode (a fall or another termination ends
it; the env's auto-reset episode after it is not counted). Per behaviour: every reward term's
return over the horizon (weight x value x dt summed, as the terms enter the reward), the return,
the return per step, V/Vmax quantiles and saturation (arms with the reference) and the share of
saturated steps that stay saturated without the upper body's terms of V, the progress along the
course gained over the rollout, the share of rollouts that ended early, by term, and the
touchdowns the reference command counted (a robot standing still must have none).

The verdict compares a tracking behaviour (reference, else checkpoint) with ``zero`` PER STEP
AT EQUAL TIME SINCE RESET, so that surviving longer is not paid for itself: for each env (same
course, same seed) the mean reward per step over the first m steps, m the shorter of the two
survivals, paired over the n rollouts: mean difference and a 95 % t interval. "ranks it above
standing" needs the interval's lower end above 0, "below" its upper end under 0; otherwise
"cannot tell at n". The difference of total returns is printed beside it, labelled: it pays
survival (a behaviour that lives longer collects more steps of positive reward).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from march.stats import mean_ci

HORIZON_STEPS = 150
"""Control steps per rollout (3 s at 50 Hz): long enough that a robot which never steps falls
behind its reference (V grows), short enough for 4 behaviours x 2 arms on a laptop."""
UPPER_STD_OPTIONS = (0.5, 0.25)
"""Upper-body (waist and arms) action std of the extra random behaviours, legs at their
configured initial std."""
PLACED_NOTE = (
    "'reference' is the kinematic G1 PLACED on the reference (the IK pose written into the "
    "simulator every step), not simulated: it cannot fall and the holonomic terms are paid by "
    "construction"
)
Act = Callable[[dict[str, Any]], torch.Tensor]


@dataclass
class BehaviourResult:
    """Per-rollout outcome of one behaviour (arrays over the n envs)."""

    name: str
    term_returns: dict[str, np.ndarray]
    """Each reward term's return over the rollout (weighted, x dt)."""
    ret: np.ndarray
    steps: np.ndarray
    reward_by_step: np.ndarray
    """(horizon, n) each step's reward (as the env sums it: weighted, x dt), NaN once the
    rollout has ended."""
    distance: np.ndarray
    ended: np.ndarray
    """The rollout ended before the horizon (fall or another termination)."""
    ended_by: dict[str, float] = field(default_factory=dict)
    """The share of rollouts each termination term ended (several can end one)."""
    touchdowns: np.ndarray | None = None
    """(n,) touchdowns the reference command counted during each rollout (None without it)."""
    v_ratio: np.ndarray | None = None
    """V/Vmax of every counted step (flattened), None without the reference."""
    v_ratio_no_upper: np.ndarray | None = None
    """The same with the 17 upper-body outputs' terms of V left out."""
    v_by_step: np.ndarray | None = None
    """(horizon,) the median V/Vmax over the rollouts still running at each step (NaN once none
    is): V at equal time since reset, which a pooled median confounds with survival (a policy
    that survives longer spends more steps where the reference has walked away)."""
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        n = len(self.ret)
        out: dict[str, Any] = {
            "behaviour": self.name,
            "n_rollouts": n,
            "return": _mean_ci(self.ret),
            "return_per_step": _mean_ci(self.ret / np.maximum(self.steps, 1)),
            "steps": float(self.steps.mean()),
            "distance_m": _mean_ci(self.distance),
            "ended_early": float(self.ended.mean()),
            "ended_by": dict(self.ended_by),
            "terms": {k: float(v.mean()) for k, v in self.term_returns.items()},
        }
        if self.v_ratio is not None and self.v_ratio.size:
            q10, q50, q90 = np.quantile(self.v_ratio, [0.1, 0.5, 0.9])
            out["v_over_vmax"] = {"p10": q10, "p50": q50, "p90": q90}
            out["saturated"] = float((self.v_ratio >= 1.0).mean())
            out["r_clf_mean"] = float(np.exp(-np.minimum(self.v_ratio, 1.0)).mean())
        if self.v_ratio_no_upper is not None and self.v_ratio_no_upper.size:
            q10, q50, q90 = np.quantile(self.v_ratio_no_upper, [0.1, 0.5, 0.9])
            out["v_over_vmax_no_upper"] = {"p10": q10, "p50": q50, "p90": q90}
            out["saturated_no_upper"] = float((self.v_ratio_no_upper >= 1.0).mean())
        if self.touchdowns is not None:
            out["touchdowns"] = int(self.touchdowns.sum())
        if self.v_by_step is not None:
            out["v_p50_by_step"] = [
                None if not np.isfinite(x) else float(x) for x in self.v_by_step
            ]
        out["notes"] = list(self.notes)
        return out


def _mean_ci(x: np.ndarray) -> dict[str, float | None]:
    """Mean and 95 % t interval over rollouts (:func:`march.stats.mean_ci`; None where
    undefined: n < 2)."""
    mean, lo, hi = mean_ci(x)
    n = len(np.asarray(x))
    return {
        "mean": mean,
        "ci_low": lo if n >= 2 else None,
        "ci_high": hi if n >= 2 else None,
        "n": n,
    }


def paired_verdict(candidate: np.ndarray, standing: np.ndarray, name: str) -> dict[str, Any]:
    """Does the reward rank ``candidate`` above ``standing``? Paired over the same rollouts:
    the mean return difference, its 95 % t interval and a verdict (see the module doc)."""
    diff = np.asarray(candidate, float) - np.asarray(standing, float)
    ci = _mean_ci(diff)
    n = ci["n"]
    lo, hi = ci["ci_low"], ci["ci_high"]
    if lo is not None and lo > 0:
        verdict = f"ranks {name} above standing"
    elif hi is not None and hi < 0:
        verdict = f"ranks {name} BELOW standing"
    else:
        verdict = f"cannot tell {name} from standing at n={n}"
    scale = abs(float(np.mean(standing))) or 1.0
    return {
        "candidate": name,
        "baseline": "zero",
        "difference": ci,
        "relative": ci["mean"] / scale,
        "verdict": verdict,
    }


def equal_time_rates(
    candidate: np.ndarray, standing: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per rollout, the mean reward per step of each behaviour over the first m steps, m the
    shorter of the two survivals; ``candidate`` and ``standing`` (horizon, n) rewards, NaN
    once a rollout ended. Returns (candidate's, standing's, m)."""
    alive_c, alive_s = np.isfinite(candidate), np.isfinite(standing)
    m = np.minimum(alive_c.sum(0), alive_s.sum(0))
    upto = np.arange(len(candidate))[:, None] < m[None, :]
    denom = np.maximum(m, 1)
    rate_c = np.where(upto, np.nan_to_num(candidate), 0.0).sum(0) / denom
    rate_s = np.where(upto, np.nan_to_num(standing), 0.0).sum(0) / denom
    return rate_c, rate_s, m


def per_step_verdict(candidate: np.ndarray, standing: np.ndarray, name: str) -> dict[str, Any]:
    """Does the reward rank ``candidate`` above ``standing`` per step at equal time since
    reset? (horizon, n) rewards each, paired over the rollouts (module docstring)."""
    rate_c, rate_s, m = equal_time_rates(candidate, standing)
    verdict = paired_verdict(rate_c, rate_s, name)
    verdict["measure"] = "reward per step over the steps both behaviours are alive"
    verdict["common_steps"] = {"mean": float(m.mean()), "min": int(m.min()), "max": int(m.max())}
    verdict["candidate_per_step"] = _mean_ci(rate_c)
    verdict["standing_per_step"] = _mean_ci(rate_s)
    return verdict


def upper_body_outputs(names: list[str]) -> np.ndarray:
    """(29,) bool: the CLF outputs that are upper-body joints (not CoM, pelvis, swing foot)."""
    from march.clf.lyapunov import UPPER_BODY_JOINTS

    return np.array([n in UPPER_BODY_JOINTS for n in names])


def roll_behaviour(env: Any, act: Act, name: str, seed: int, horizon: int) -> BehaviourResult:
    """Roll ``act`` from the seeded start for ``horizon`` steps (see the module doc)."""
    from march.env.build import reseed_env
    from march.env.course import CourseRuler

    rm = env.reward_manager
    term_names = list(rm.active_terms)
    dt = float(env.step_dt) if getattr(rm, "_scale_by_dt", True) else 1.0  # as term_meter
    ruler = CourseRuler(env)
    meter = getattr(env, "clf_meter", None)
    upper = None
    if meter is not None:
        from march.clf.diagnostics import output_terms

        names = list(meter.term.clf.cfg.output_names)
        upper = torch.as_tensor(upper_body_outputs(names), device=env.device)
    e, dev = env.num_envs, env.device
    reseed_env(env, seed)  # also restarts the per-env planner streams (issue 55)
    torch.manual_seed(seed)
    obs, _ = env.reset()
    alive = torch.ones(e, dtype=torch.bool, device=dev)
    steps = torch.zeros(e, device=dev)
    terms = torch.zeros(e, len(term_names), device=dev, dtype=torch.float64)
    ret = torch.zeros(e, device=dev, dtype=torch.float64)
    ended = torch.zeros(e, dtype=torch.bool, device=dev)
    tm = env.termination_manager
    end_terms = [k for k, c in zip(tm.active_terms, tm._term_cfgs, strict=True) if not c.time_out]
    ended_by = torch.zeros(e, len(end_terms), device=dev)
    start = ruler.progress().clone()
    distance = start.clone()
    ratios: list[torch.Tensor] = []
    ratios_no_upper: list[torch.Tensor] = []
    rewards: list[torch.Tensor] = []
    touchdowns = torch.zeros(e, dtype=torch.long, device=dev)
    with torch.no_grad():
        for _ in range(horizon):
            before = None if meter is None else meter.term.touchdown_count.clone()
            obs, reward, terminated, truncated, _ = env.step(act(obs))
            w = alive.double()
            terms += rm._step_reward.double() * dt * w[:, None]
            ret += reward.double() * w
            rewards.append(torch.where(alive, reward.double(), torch.nan))
            steps += alive.float()
            if meter is not None:
                v_max = meter.stats.v_max
                ratios.append(torch.where(alive, meter.term.v / v_max, torch.nan))
                v_terms = output_terms(meter.term.v_products)
                lower = v_terms[:, ~upper].sum(-1)
                ratios_no_upper.append(torch.where(alive, lower / v_max, torch.nan))
                touchdowns += (meter.term.touchdown_count - before) * alive.long()
            done = terminated | truncated
            ended |= alive & terminated
            if end_terms:
                by = torch.stack([tm._term_dones[k] for k in end_terms], dim=1)
                ended_by += (by & (alive & terminated)[:, None]).float()
            # progress before the auto-reset is not readable after it: keep the last alive one
            distance = torch.where(alive & ~done, ruler.progress(), distance)
            alive &= ~done
    v = by_step = v_no_upper = None
    if ratios:
        r = torch.stack(ratios).cpu().numpy()
        v = r[np.isfinite(r)]
        r_lower = torch.stack(ratios_no_upper).cpu().numpy()
        v_no_upper = r_lower[np.isfinite(r_lower)]
        alive_any = np.isfinite(r).any(1)
        by_step = np.full(len(r), np.nan)
        by_step[alive_any] = np.nanmedian(r[alive_any], axis=1)
    t = terms.cpu().numpy()
    return BehaviourResult(
        name=name,
        term_returns={k: t[:, i] for i, k in enumerate(term_names)},
        ret=ret.cpu().numpy(),
        steps=steps.cpu().numpy(),
        reward_by_step=torch.stack(rewards).cpu().numpy(),
        touchdowns=None if meter is None else touchdowns.cpu().numpy(),
        distance=(distance - start).cpu().numpy(),
        ended=ended.cpu().numpy(),
        ended_by={k: float(v) for k, v in zip(end_terms, ended_by.mean(0).tolist(), strict=True)},
        v_ratio=v,
        v_ratio_no_upper=v_no_upper,
        v_by_step=by_step,
    )


def behaviours(env: Any, cfg: Any, policy: Act | None) -> dict[str, Act]:
    """The canonical behaviours available on this env (see the module doc)."""
    from march.env.joint_groups import action_joint_names, per_joint

    n_act = env.action_manager.total_action_dim
    e, dev = env.num_envs, env.device
    out: dict[str, Act] = {"zero": lambda obs: torch.zeros(e, n_act, device=dev)}
    names = action_joint_names(env)
    init = dict(cfg.teacher.group_init_std)
    for name, stds in random_options(init).items():
        out[name] = random_behaviour(per_joint(names, stds).to(dev), e, int(cfg.seed))
    if policy is not None:
        out["checkpoint"] = policy
    if getattr(env, "clf_meter", None) is not None:
        from march.audit.kinematic_reference import KinematicReference

        tracker = KinematicReference(env)
        out["reference"] = lambda obs: tracker.act(env)
    return out


def random_options(init: dict[str, float]) -> dict[str, dict[str, float]]:
    """Behaviour name -> std per joint group: ``random`` at the configured initial std
    ``init`` (group -> std), then the upper body (waist and arms) at each of
    :data:`UPPER_STD_OPTIONS` with the legs at theirs (options equal to ``random`` skipped)."""
    out = {"random": dict(init)}
    for std in UPPER_STD_OPTIONS:
        option = {"legs": init["legs"], "waist": std, "arms": std}
        if option != init:
            out[f"random upper {std:g}"] = option
    return out


def random_behaviour(std: torch.Tensor, num_envs: int, seed: int) -> Act:
    """Actions N(0, diag(std^2)) (``std`` (A,) per joint), as PPO's initial policy draws
    them around its zero mean, from its own seeded generator."""
    gen = torch.Generator(device=std.device)
    gen.manual_seed(seed)

    def act(obs: dict[str, Any]) -> torch.Tensor:
        noise = torch.randn(num_envs, len(std), device=std.device, generator=gen)
        return noise * std

    return act


def audit_arm(env: Any, cfg: Any, policy: Act | None, horizon: int = HORIZON_STEPS) -> dict:
    """Roll every behaviour and judge the arm (the JSON report's ``arm`` entry)."""
    results: dict[str, BehaviourResult] = {}
    for name, act in behaviours(env, cfg, policy).items():
        results[name] = roll_behaviour(env, act, name, int(cfg.seed), horizon)
        print(f"[audit] {cfg.reward.name}: {name} rolled ({env.num_envs} x {horizon})", flush=True)
    zero = results["zero"]
    verdicts = [
        per_step_verdict(results[name].reward_by_step, zero.reward_by_step, name)
        for name in ("reference", "checkpoint")
        if name in results
    ]
    survival = [
        paired_verdict(results[name].ret, zero.ret, name) | {"measure": "total return"}
        for name in ("reference", "checkpoint")
        if name in results
    ]
    return {
        "reward": cfg.reward.name,
        "num_envs": int(env.num_envs),
        "horizon_steps": horizon,
        "step_dt": float(env.step_dt),
        "seed": int(cfg.seed),
        "behaviours": [r.summary() for r in results.values()],
        "verdicts": verdicts,
        "total_return_differences": survival,
        "notes": [PLACED_NOTE] if "reference" in results else [],
        "raw": {
            k: {"return": r.ret.tolist(), "steps": r.steps.tolist()} for k, r in results.items()
        },
    }
