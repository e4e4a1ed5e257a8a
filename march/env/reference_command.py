"""The ``reference`` command term: stage (1) of the CLF teacher inside the mjlab env.

It keeps, per env, the walking state the CLF rewards need: which foot is the stance foot and
where it touched down, the current footstep plan (N = 4 steps from
:func:`march.reference.planner.plan_footsteps`), the time ``tau`` since the step began and its
planned duration, the reference outputs ``y_ref`` (:func:`march.reference.trajectory.reference_at`)
and the measured outputs ``y_sim`` (:mod:`march.env.clf_outputs`), and the CLF value V with its
derivative.

Decisions (documented here once; the README repeats them)
- **Velocity command, in the course frame** (issue 10). mjlab's ``twist`` command stays the one
  velocity command of both reward arms (the proprioceptive ``command`` observation and the
  distillation code read it): a forward speed sampled once per episode from ``env.command_vx``
  (``eval.command_vx`` in evaluation), lateral speed ``env.command_vy`` (0 by default), and a
  yaw rate that is mjlab's heading controller toward the course heading (march.env.build). This
  term plans with the forward speed along the course direction (``Footholds.direction``) and
  the lateral speed across it, whatever the robot's heading; the pelvis- and swing-yaw
  references are the course heading (yaw rate 0); why: README, "Velocity command".
- **Start from standing.** The first step of an episode ramps its CoM reference from rest at the
  measured CoM into the HLIP orbit (``march.reference.trajectory``, ``StepState.ramp``); later
  steps carry the previous reference's CoM state (below, "Touchdown").
- **Initial stance (episode reset).** The foot that is further behind along the course direction
  is the stance foot; when the feet are level within ``stance_tie_m`` (the usual spawn) the left
  foot is the stance foot, so the right foot swings first. The first plan starts from that foot
  on the start platform. Robot state is only valid after mjlab's post-reset ``forward()``, so a
  reset marks the env pending and the plan is made in the command update that follows it.
- **Touchdown** (issue 55: only a real one). The swing foot's contact (``found`` of the
  ``feet_ground_contact`` sensor, per foot) counts as a touchdown once the foot has been off the
  ground at some update since the step began (``swing_lifted``: out of contact and
  ``lift_min_height`` above where it started; the sensor flickers while a foot rocks in place)
  and ``tau >= touchdown_min_fraction * duration`` (author: 0.6), while the pelvis tilts less
  than ``touchdown_max_tilt`` from upright; earlier contacts (scuffs), a foot that never left the
  ground and the feet of a robot that is falling over are no touchdown (a standing robot's
  steps time out instead, below). At
  a touchdown the swing foot becomes the stance foot, a new plan is made from its actual
  position (only for the envs that touched down), the new step's reference starts from the
  actual stance foot and carries the previous reference's CoM state and pelvis roll and pitch
  (``reference.com_anchoring=continuous``, :mod:`march.reference.com_carry`; ``stance``: the
  orbit anchored at the new stance foot, which jumps), lift-off = the new swing foot's current
  position, ``tau`` restarts and ``step_switched`` is set so the V history restarts (no
  derivative across the switch).
- **Timeout.** If the swing foot has not touched down by ``tau >= touchdown_timeout_fraction *
  duration`` the step is restarted instead of switched: the swing foot is still in the air, so
  making it the stance foot would anchor the reference (and the holonomic terms) on a foot that
  bears no weight. The plan is remade from the same stance foot, the new swing starts where the
  foot is, ``tau`` restarts and ``step_switched`` is set (counted in ``forced_count``). The
  CoM reference carries on continuously from where the old step's was (continuous anchoring):
  a robot that stands still sees a reference that keeps stepping in place of it, one restart
  every 1.5 T, never a jump.
- **CoM and outputs**: the measured outputs y_sim are documented with their code in
  :mod:`march.env.clf_outputs`.
- **r_dclf clip**: :attr:`ReferenceCommandCfg.clf`.
- **Replanning without host syncs** (issues 11, 41): one planner batch per update, of a size
  that depends on the host-known reset count only (``capacity``, or a power of two up to E when
  more envs reset): mjlab's reset envs first, then the due touchdowns and timeouts, then
  padding rows that are planned and discarded (:mod:`march.env.replan_queue`).
- **When V is evaluated.** mjlab computes rewards *before* the command update of a step. V is
  computed once per env step, lazily, by the first CLF reward term that asks
  (:meth:`ReferenceCommand.clf_state`): y_sim of the state the action produced against y_ref at
  ``tau + step_dt`` (the same instant), then ``VHistory.update``. Both CLF terms read that same V.
  The command update then detects touchdowns and refreshes ``y_ref``/``y_sim`` at the new ``tau``
  for the observations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING

import torch
from mjlab.managers.command_manager import CommandTerm, CommandTermCfg

from march.clf.lyapunov import CLF_OUTPUT_NAMES, UPPER_BODY_JOINTS, ClfCfg, ClfModel, VHistory
from march.compiled_math import maybe_fused
from march.env import rollout_draws
from march.env.clf_outputs import (
    body_masses,
    body_rows,
    euler_from_matrix,
    measured_outputs,
    reference_in_base_frame,
    stance_foot_state,
)
from march.env.course import foothold_table
from march.env.masked_rows import MaskedRows
from march.env.replan_queue import ReplanQueue
from march.env.step_cache import root_frame, site_pos, site_xmat
from march.keyed_random import RowStreams
from march.reference.fused_reference import reference_outputs, reference_tables
from march.reference.hlip import HlipCfg
from march.reference.plan_tables import course_frame, plan_tables
from march.reference.planner import Plan, plan_footsteps
from march.reference.planner_cfg import PlannerCfg
from march.reference.trajectory import ReferenceCfg, StepState, angle_mask, step_state_from_plan
from march.world.footholds import Footholds

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

NUM_OUTPUTS = len(CLF_OUTPUT_NAMES)
CARRIED = 5
"""Reference outputs a new step carries from the previous one (continuous anchoring): CoM x, y,
z, pelvis roll and pitch, the first columns of ``CLF_OUTPUT_NAMES``."""
STEP_FIELDS = tuple(f.name for f in fields(StepState))
"""The per-env tensors of a ``StepState``."""
PLAN_STATE = (
    "stance_anchor",
    "plan_footholds",
    "plan_durations",
    "plan_feasible",
    "plan_stalled",
    "tau",
    "step_switched",
    "swing_lifted",
)
"""The term's own per-env tensors a new step sets (besides the ``StepState``)."""


@dataclass(kw_only=True)
class ReferenceCommandCfg(CommandTermCfg):
    """Configuration of the ``reference`` command term (defaults: author values, SPEC §2)."""

    resampling_time_range: tuple[float, float] = (1.0e9, 1.0e9)
    """Only episode resets restart the term (no timed resampling)."""
    entity_name: str = "robot"
    velocity_command: str = "twist"
    """The velocity command term this one reads (v_D and the yaw rate)."""
    contact_sensor: str = "feet_ground_contact"
    foot_bodies: tuple[str, str] = ("left_ankle_roll_link", "right_ankle_roll_link")
    """Contact-sensor primaries of the left and right foot."""
    foot_sites: tuple[str, str] = ("left_foot", "right_foot")
    """Sites tracked as the feet (sole level)."""
    touchdown_min_fraction: float = 0.6
    """A swing-foot contact counts as touchdown from tau >= this x planned duration (author 0.6)."""
    lift_min_height: float = 0.02
    """A swing foot has left the ground once it is out of contact and this much above where it
    was when the step began [m] (a contact sensor that flickers while a foot rocks in place is
    no lift-off; issue 55)."""
    touchdown_max_tilt: float = 0.35
    """A swing-foot contact is a touchdown only while the pelvis tilts less than this from
    upright [rad] (20 deg): a falling robot's feet lift and land without stepping (zero action
    counted 2 such contacts at 0.58-0.62 rad; a walking reference leans 0.03 rad; the episode
    ends at 50 deg, ``termination.tilt_limit_deg``). Issue 55."""
    touchdown_timeout_fraction: float = 1.5
    """No touchdown by tau >= this x planned duration: restart the step from the same stance."""
    stance_tie_m: float = 0.01
    """At reset, feet within this along the course count as level (then the left foot stands)."""
    replan_capacity_fraction: float = 0.125
    """Share of the envs whose touchdown or timeout can be planned in one update (the fixed
    size of the per-step planner batch; module docstring, "Replanning without host syncs")."""
    replan_capacity_min: int = 8
    """The per-update planner batch holds at least this many envs (or all of them)."""
    replan_only_when_due: bool = False
    """Call the planner only in updates where an env is reset, touches down or times out (one
    host read per update). On CPU a host read is free and the planner's fixed-size batch is most
    of march's own per-step cost (41 of 56 ms per step at 32 envs, docs/benchmarks.md), so the
    cpu preset turns it on (``compute.replan_only_when_due``); on a GPU the read is a sync per
    step and the fixed batch never branches on data: off."""
    compile_math: bool = False
    """``torch.compile`` (dynamic shapes) :func:`reference_at` (``compute.compile_math``)."""
    planner_seed: int | None = 0
    """Seed of the planner's random draws: one counter-based stream per env keyed by (seed,
    env index) (``ReferenceCommand.planner_streams``; an evaluation keys them by rollout)."""
    planner: PlannerCfg = field(default_factory=PlannerCfg)
    reference: ReferenceCfg = field(default_factory=ReferenceCfg)
    hlip: HlipCfg = field(default_factory=HlipCfg)
    clf: ClfCfg = field(default_factory=lambda: ClfCfg(dclf_clip=1.0))
    """CLF outputs and normalisers. r_dclf is clipped at -1 (``dclf_clip = 1.0``, the author's
    ``clip(., 0, 1)``; the paper prints no clip): unclipped, under the initial policy's action
    noise (std 1) the weighted r_dclf averages about -22 per step against +3.7 for the weighted
    r_clf (8 envs, 150 steps), so the decrease term swamps every other signal; clipped it
    averages about -0.5."""

    def capacity(self, num_envs: int) -> int:
        """Envs planned per update for touchdowns and timeouts, for ``num_envs`` envs."""
        by_share = math.ceil(self.replan_capacity_fraction * num_envs)
        return min(num_envs, max(self.replan_capacity_min, by_share))

    def build(self, env: ManagerBasedRlEnv) -> ReferenceCommand:
        return ReferenceCommand(self, env)

    def __post_init__(self) -> None:
        if not 0.0 <= self.touchdown_min_fraction < self.touchdown_timeout_fraction:
            raise ValueError("need 0 <= touchdown_min_fraction < touchdown_timeout_fraction")
        if not 0.0 < self.touchdown_max_tilt <= math.pi:
            raise ValueError("need 0 < touchdown_max_tilt <= pi")
        if not 0.0 < self.replan_capacity_fraction <= 1.0 or self.replan_capacity_min < 1:
            raise ValueError("need 0 < replan_capacity_fraction <= 1 and replan_capacity_min >= 1")
        if not math.isclose(self.planner.step_width, self.hlip.step_width):
            raise ValueError("planner.step_width and hlip.step_width must agree")


class ReferenceCommand(CommandTerm):
    """Planner + reference + CLF state per env (see the module docstring)."""

    cfg: ReferenceCommandCfg

    def __init__(self, cfg: ReferenceCommandCfg, env: ManagerBasedRlEnv):
        super().__init__(cfg, env)
        e, dev = self.num_envs, self.device
        self.robot = env.scene[cfg.entity_name]
        self.sensor = env.scene[cfg.contact_sensor]
        names = list(self.sensor.primary_names)
        self._contact_idx = torch.tensor(
            [names.index(b) for b in cfg.foot_bodies], device=dev, dtype=torch.long
        )
        site_ids, _ = self.robot.find_sites(cfg.foot_sites, preserve_order=True)
        self._site_ids = torch.tensor(site_ids, device=dev, dtype=torch.long)
        joint_ids, _ = self.robot.find_joints(UPPER_BODY_JOINTS, preserve_order=True)
        self._upper_ids = torch.tensor(joint_ids, device=dev, dtype=torch.long)
        self._body_ids = torch.as_tensor(self.robot.indexing.body_ids, device=dev).long()
        body_rows(env, self.robot)  # found here, once (a host read), not in the first step
        self._root_body = int(self.robot.indexing.root_body_id)

        self.table = foothold_table(env)
        self.footholds: Footholds = self._lookup_footholds(torch.arange(e, device=dev))
        """(E envs) the stones of each env's current course (refreshed on reset)."""

        self.clf = ClfModel(cfg.clf, device=dev)
        """The single CLF model of this env (P from CARE, built once)."""
        self.v_history = VHistory(e, env.step_dt, device=dev)
        self.mask = angle_mask(len(UPPER_BODY_JOINTS), device=dev)
        self._reference_outputs = maybe_fused(reference_outputs, cfg.compile_math)
        self._ref_tables = reference_tables(
            cfg.reference, len(UPPER_BODY_JOINTS), torch.float32, dev
        )
        self.generator = torch.Generator(device=dev)
        self.generator.manual_seed(int(cfg.planner_seed if cfg.planner_seed is not None else 0))
        self.planner_streams = RowStreams(e, dev)
        """The planner's random draws, one counter-based stream per env keyed by (planner_seed,
        env index) (issue 55): an env's plans do not depend on the batch, its place in the
        planner's batch or the other envs' touchdowns (march.keyed_random). ``generator`` is
        kept for callers that plan with shared draws."""
        self.planner_streams.assign(int(cfg.planner_seed or 0), 0)

        n = cfg.planner.num_steps
        zeros3 = torch.zeros(e, 3, device=dev)
        self.stance_is_left = torch.ones(e, dtype=torch.bool, device=dev)
        """(E,) the stance foot is the left one."""
        self.stance_anchor = zeros3.clone()
        """(E, 3) stance foot site position at its touchdown (world) [m]: holonomic anchor."""
        self.plan_footholds = torch.zeros(e, n, 3, device=dev)
        """(E, N, 3) current plan: footholds (stone-top z), world [m]."""
        self.plan_durations = torch.full((e, n), cfg.planner.nominal_duration, device=dev)
        """(E, N) current plan: step durations [s]."""
        self.plan_feasible = torch.ones(e, dtype=torch.bool, device=dev)
        """(E,) the current plan met every planner constraint."""
        self.plan_stalled = torch.zeros(e, dtype=torch.bool, device=dev)
        """(E,) the current plan's stall flag (``Plan.stalled``): some step could not keep the
        commanded pace while the goal lay ahead."""
        self.tau = torch.zeros(e, device=dev)
        """(E,) time since the current step began [s]."""
        self.yaw0 = torch.zeros(e, device=dev)
        """(E,) pelvis-yaw reference: the course heading [rad] (set at each episode start)."""
        self.step_switched = torch.zeros(e, dtype=torch.bool, device=dev)
        """(E,) the reference switched (touchdown, restart or reset) in the last update."""
        self.swing_lifted = torch.zeros(e, dtype=torch.bool, device=dev)
        """(E,) the swing foot has been off the ground at an update since the step began: only
        then does its contact end the step (a real touchdown)."""
        self.touchdown_count = torch.zeros(e, dtype=torch.long, device=dev)
        """(E,) touchdowns (stance switches) since the env was built."""
        self.forced_count = torch.zeros(e, dtype=torch.long, device=dev)
        """(E,) timeout restarts since the env was built."""
        self.replan_count = torch.zeros(e, dtype=torch.long, device=dev)
        """(E,) plans made (resets, touchdowns, restarts) since the env was built."""
        self.queue = ReplanQueue(e, cfg.capacity(e), dev)
        """The resets to plan and the touchdowns / timeouts waiting for the planner batch."""
        self._all_envs = torch.ones(e, dtype=torch.bool, device=dev)
        self._mass_key: tuple[int, int] | None = None
        self._mass_cache: tuple[torch.Tensor, torch.Tensor] | None = None
        self._dt: float | torch.Tensor = 0.0
        self.step = StepState(
            stance_pos=zeros3.clone(),
            stance_is_left=self.stance_is_left.clone(),
            swing_start=zeros3.clone(),
            target=zeros3.clone(),
            next_target=zeros3.clone(),
            duration=self.plan_durations[:, 0].clone(),
            next_duration=self.plan_durations[:, 1].clone(),
            yaw0=torch.zeros(e, device=dev),
            yaw_rate=torch.zeros(e, device=dev),
            axis=torch.tensor([[1.0, 0.0]], device=dev).repeat(e, 1),
            ramp=torch.zeros(e, dtype=torch.bool, device=dev),
            ramp_from=torch.zeros(e, 2, device=dev),
            com_from_pos=zeros3.clone(),
            com_from_vel=zeros3.clone(),
            pelvis_from_pos=torch.zeros(e, 2, device=dev),
            pelvis_from_vel=torch.zeros(e, 2, device=dev),
            z0=torch.full((e,), cfg.hlip.z0, device=dev),
            swing_from_pitch=torch.zeros(e, device=dev),
        )
        self.y_ref_pos = torch.zeros(e, NUM_OUTPUTS, device=dev)
        """(E, 29) reference outputs at the current tau (CLF_OUTPUT_NAMES order)."""
        self.y_ref_vel = torch.zeros(e, NUM_OUTPUTS, device=dev)
        self._y_sim: tuple[torch.Tensor, torch.Tensor] | None = None
        self._next_ref: tuple[tuple[int, int], torch.Tensor, torch.Tensor] | None = None
        """y_ref at tau + step_dt from the refresh (the next :meth:`clf_state`'s) and its key."""
        self._step_version = 0
        self.v = torch.zeros(e, device=dev)
        """(E,) CLF value V of the last env step (see :meth:`clf_state`)."""
        self.vdot = torch.zeros(e, device=dev)
        self.v_valid = torch.zeros(e, dtype=torch.bool, device=dev)
        self.v_products = torch.zeros(e, 2 * NUM_OUTPUTS, device=dev)
        """(E, 58) the interleaved products whose sum is V (pairs: each output's term of V)."""
        self._v_step = -1
        self.metrics["touchdowns"] = torch.zeros(e, device=dev)
        self.metrics["timeouts"] = torch.zeros(e, device=dev)
        # What _new_step writes: one index_put per tensor (march.env.masked_rows).
        owners = {f"step.{f}": (self.step, f) for f in STEP_FIELDS}
        self._rows = MaskedRows(e, {**owners, **{name: (self, name) for name in PLAN_STATE}})

    # ---------------------------------------------------------------- mjlab interface

    @property
    def command(self) -> torch.Tensor:
        """The privileged reference observation (E, 2*29 + 3N + 2); see :meth:`observation`."""
        return self.observation()

    def compute(self, dt: float | torch.Tensor, env_ids: torch.Tensor | None = None) -> None:
        """mjlab's ``CommandTerm.compute`` without its resampling timer: this term never
        resamples on time (``resampling_time_range`` is 1e9 s), and the timer's
        ``(time_left <= 0).nonzero()`` would be a host sync per step."""
        self._dt = dt  # _update_command advances tau by it (per env on the auto-reset path)
        self._update_command(env_ids)

    def reset(self, env_ids: torch.Tensor | slice | None) -> dict[str, torch.Tensor]:
        """mjlab's ``CommandTerm.reset`` with the episode metrics kept on the device (0-d
        tensors, not ``.item()``: no host sync per reset)."""
        assert isinstance(env_ids, torch.Tensor)
        extras = {}
        for name, value in self.metrics.items():
            extras[name] = value[env_ids].mean()
            value[env_ids] = 0.0
        self.command_counter[env_ids] = 0
        self._resample(env_ids)
        return extras

    def _update_metrics(self) -> None:  # counted where they happen (_update_command)
        pass

    def _resample_command(self, env_ids: torch.Tensor) -> None:
        """Episode reset: new course cell (the curriculum ran first), plan after forward().

        ``env_ids`` is host-sized (mjlab found the reset envs), so the episode starts are planned
        as exactly that batch in the next :meth:`_update_command`, without a host sync here.
        """
        self.queue.add_resets(env_ids)
        fh = self._lookup_footholds(env_ids)
        for name in ("center", "half_size", "valid", "start_xy", "direction"):
            getattr(self.footholds, name)[env_ids] = getattr(fh, name)
        self.footholds.goal_distance[env_ids] = fh.goal_distance
        self.footholds.course_length[env_ids] = fh.course_length
        self.v_history.reset(env_ids)
        self._step_version += 1
        self.tau[env_ids] = 0.0
        self.plan_feasible[env_ids] = True

    def _update_command(self, env_ids: torch.Tensor | None) -> None:
        """Advance tau, start pending episodes, detect touchdowns and timeouts, replan, refresh
        the outputs: one planner call per update, on a batch of one of a few fixed sizes
        (:meth:`march.env.replan_queue.ReplanQueue.next_batch`), and no host synchronisation
        (module docstring, "Replanning without host syncs")."""
        e = self.num_envs
        if env_ids is None:
            active = self._all_envs
        else:
            active = torch.zeros(e, dtype=torch.bool, device=self.device)
            active[env_ids] = True
        self.step_switched &= ~active
        # The reference at the new tau (what a step that begins now carries): the last refresh
        # computed it (y_ref at tau + step_dt) unless something changed since or dt differs.
        cached = self._next_ref
        com_now = None
        if (
            cached is not None
            and cached[0] == self._ref_key()
            and isinstance(self._dt, float)
            and self._dt == self._env.step_dt
        ):
            com_now = (cached[1][:, :CARRIED], cached[2][:, :CARRIED])
        self._step_version += 1
        self.tau += active * self._dt  # dt: a float, or per env on mjlab's auto-reset path

        resets = self.queue.take_resets()
        running = active & ~self.queue.is_reset
        contact = self.foot_contact()
        swing_contact = torch.where(self.stance_is_left, contact[:, 1], contact[:, 0])
        feet_z = self.feet_pos()[..., 2]
        swing_z = torch.where(self.stance_is_left, feet_z[:, 1], feet_z[:, 0])
        high = swing_z > self.step.swing_start[:, 2] + self.cfg.lift_min_height
        self.swing_lifted |= active & ~swing_contact & high
        dur = self.step.duration
        due = self.tau >= self.cfg.touchdown_min_fraction * dur
        upright = self.pelvis_tilt_cos() >= math.cos(self.cfg.touchdown_max_tilt)  # not falling
        touchdown = running & swing_contact & self.swing_lifted & due & upright
        timeout = running & (self.tau >= self.cfg.touchdown_timeout_fraction * dur)
        # One planner batch of a fixed size: the resets, then due envs, then padding.
        batch = self.queue.next_batch(touchdown, timeout, active)
        sel, serve, flip = batch.sel, batch.serve, batch.flip
        forced = serve & ~flip
        self.stance_is_left[sel] = self.stance_is_left[sel] ^ flip
        # sel holds distinct envs: index_add_ is the gather + add + index_put it replaces
        self.touchdown_count.index_add_(0, sel, flip.long())
        self.forced_count.index_add_(0, sel, forced.long())
        self.metrics["touchdowns"].index_add_(0, sel, flip.float())
        self.metrics["timeouts"].index_add_(0, sel, forced.float())

        if batch.num_resets:
            self._start_episode(resets)
        # On CPU (replan_only_when_due) one host read skips the planner when no row of the batch
        # is applied: the padding rows' plans are discarded and no stream advances for them, so
        # the skip changes no number (tests/test_env_reference.py compares both paths).
        if (
            batch.num_resets
            or not self.cfg.replan_only_when_due
            or bool(batch.apply.any())  # a host read: CPU only (replan_only_when_due)
        ):
            self._new_step(batch.ids, apply=batch.apply, ramp=batch.ramp, com_now=com_now)
        self._refresh_outputs()

    # ---------------------------------------------------------------- planning

    def _lookup_footholds(self, env_ids: torch.Tensor) -> Footholds:
        terrain = self._env.scene.terrain
        return self.table.for_envs(
            terrain.terrain_levels[env_ids],
            terrain.terrain_types[env_ids],
            self._env.scene.env_origins[env_ids],
        )

    def feet_pos(self) -> torch.Tensor:
        """(E, 2, 3) left and right foot site positions, world [m] (the two sites only: mjlab's
        ``site_pos_w`` converts the pose of every site on each access)."""
        return site_pos(self._env, tuple(self.cfg.foot_sites), self.cfg.entity_name)

    def pelvis_tilt_cos(self) -> torch.Tensor:
        """(E,) cosine of the pelvis's tilt from upright: R22 of the root body's rotation matrix
        (MuJoCo's xmat, row-major; one read, no quaternion maths)."""
        return self._env.sim.data.xmat[:, self._root_body].reshape(self.num_envs, 9)[:, 8]

    def foot_contact(self) -> torch.Tensor:
        """(E, 2) bool: left / right foot touches the terrain."""
        found = self.sensor.data.found
        return found[:, self._contact_idx] > 0

    def _start_episode(self, env_ids: torch.Tensor) -> None:
        """Initial stance foot and course heading of the envs starting an episode (their first
        plan is made in the same update's planner call)."""
        feet = self.feet_pos()[env_ids]
        axis, _ = course_frame(self.footholds.index(env_ids))
        along = (feet[..., :2] * axis[:, None]).sum(-1)  # (n, 2)
        right_behind = along[:, 1] < along[:, 0] - self.cfg.stance_tie_m
        self.stance_is_left[env_ids] = ~right_behind
        self.yaw0[env_ids] = torch.atan2(axis[:, 1], axis[:, 0])  # the course heading

    def replan(self, env_ids: torch.Tensor) -> Plan:
        """Plan from the current stance foot of ``env_ids`` and make step 0 the current step.

        Used at reset, touchdown and timeout; public so tools and tests can force a replan.
        """
        return self._new_step(env_ids)

    def _new_step(
        self,
        env_ids: torch.Tensor,
        apply: torch.Tensor | None = None,
        ramp: torch.Tensor | None = None,
        com_now: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> Plan:
        """Replan ``env_ids`` (no duplicates, except repeated resets) from their stance foot and
        start step 0 of the plan where ``apply`` (n,) is True (all if None); the other rows are
        planned but left as they were (the fixed-size batch of :meth:`_update_command`).
        ``ramp`` (n,): the env starts from standing (episode start): its CoM reference ramps
        from the measured CoM (and carries it, at rest). ``com_now``: (E, >= 5) reference
        positions and velocities at the current tau, CoM xyz then pelvis roll and pitch
        (computed here when None), carried into the new step
        (``reference.com_anchoring=continuous``)."""
        n = env_ids.numel()
        if apply is None:
            apply = torch.ones(n, dtype=torch.bool, device=self.device)
        feet = self.feet_pos()[env_ids]  # (n, 2, 3)
        left = self.stance_is_left[env_ids]
        stance = torch.where(left[:, None], feet[:, 0], feet[:, 1])
        swing = torch.where(left[:, None], feet[:, 1], feet[:, 0])
        # The planner's per-env tables of every env, then the batch's rows (two index ops, not
        # one per Footholds field); their course frame is course_frame's, bit for bit.
        tables = plan_tables(self.footholds, self.cfg.planner).index(env_ids)
        axis, lat = tables.axis, tables.lat
        # The planner's world-frame command: the twist's forward speed along the course and its
        # lateral speed across it (module docstring; the yaw rate is unused by the planner).
        twist = self._env.command_manager.get_command(self.cfg.velocity_command)[env_ids]
        cmd = twist[:, 0:1] * axis + twist[:, 1:2] * lat
        keyed = rollout_draws.active(self._env)
        if keyed is None:  # each env's own stream, advanced only where its plan is applied
            ids = env_ids.long()

            def own(shape: tuple[int, ...]) -> torch.Tensor:
                return self.planner_streams.uniform(ids, shape, torch.float32, advance=apply)

            row_uniform = own
        else:  # an evaluation: each env's samples from its rollout's stream (rollout_draws)
            row_uniform = keyed.planner_uniform(env_ids, apply)
        plan = plan_footsteps(
            stance[:, :2],
            left,
            cmd,
            tables,
            self.cfg.planner,
            self.generator,
            compiled=self.cfg.compile_math,
            row_uniform=row_uniform,
        )
        com = self._env.sim.data.subtree_com[env_ids, self._root_body]
        if com_now is None:
            com_now = self.reference(self.tau)
        ramp = torch.zeros_like(apply) if ramp is None else ramp
        # An episode start carries the measured CoM at rest; a walk the reference's CoM state.
        held = ramp[:, None]
        com_from = (
            torch.where(held, com, com_now[0][env_ids, :3]),
            torch.where(held, 0.0, com_now[1][env_ids, :3]),
        )
        # An episode start carries the pelvis at rest (level roll, the pitch offset).
        rest = torch.zeros_like(com_now[0][env_ids, 3:5])
        rest[:, 1] = self.cfg.reference.pitch_offset
        pelvis_from = (
            torch.where(held, rest, com_now[0][env_ids, 3:5]),
            torch.where(held, 0.0, com_now[1][env_ids, 3:5]),
        )
        # The new swing foot's pitch, carried into its reference (reference.swing_pitch_carry;
        # a foot that lifted its heel leaves the ground toe down): read only when used.
        if self.cfg.reference.swing_pitch_carry > 0.0:
            mats = site_xmat(self._env, tuple(self.cfg.foot_sites), self.cfg.entity_name)
            mats = mats[env_ids]
            foot = torch.where(left[:, None, None], mats[:, 1], mats[:, 0])
            swing_pitch = euler_from_matrix(foot)[:, 1]
        else:
            swing_pitch = torch.zeros_like(swing[:, 0])
        st = step_state_from_plan(
            plan,
            stance_pos=plan.start,
            swing_start=swing,
            yaw0=self.yaw0[env_ids],
            yaw_rate=torch.zeros_like(cmd[:, 0]),  # the yaw reference holds the course heading
            axis=axis,
            ramp_from=com[:, :2],
            com_from=com_from,
            cfg=self.cfg.reference,
            hlip=self.cfg.hlip,
            pelvis_from=pelvis_from,
            swing_from_pitch=swing_pitch,
        )
        st.ramp = ramp

        values = {f"step.{name}": getattr(st, name) for name in STEP_FIELDS}
        values.update(
            stance_anchor=stance,
            plan_footholds=plan.footholds,
            plan_durations=plan.durations,
            plan_feasible=plan.feasible,
            plan_stalled=plan.stalled,
            tau=self.tau.new_zeros(n),
            step_switched=torch.ones_like(apply),
            swing_lifted=torch.zeros_like(apply),
        )
        self._rows.write(env_ids, apply, values)
        self._step_version += 1
        self.replan_count[env_ids] += apply.long()
        switched = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        switched[env_ids] = apply
        self.v_history.forget(switched)
        return plan

    # ---------------------------------------------------------------- outputs and V

    def reference(self, tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(E, 29) reference positions and velocities at time ``tau`` into the current step
        (:func:`march.reference.trajectory.reference_outputs`: ``reference_at`` flattened)."""
        return self._reference_outputs(
            self.step,
            tau,
            self.cfg.reference,
            self.cfg.hlip,
            len(UPPER_BODY_JOINTS),
            self._ref_tables,
        )

    def _masses(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(W|1, B) robot body masses and their (W|1, 1) sums, kept while the model's mass
        tensor is the same one at the same version: DR writes masses at startup (and an
        evaluation's waves again, march.env.rollout_draws), each write bumps the version and the
        next call reads them afresh (host-side attributes only: no sync)."""
        mass = self._env.sim.model.body_mass
        key = (id(mass), -1 if mass.is_inference() else mass._version)
        if self._mass_key != key:
            self._mass_key, self._mass_cache = key, body_masses(self._env, self._body_ids)
        return self._mass_cache

    def measured(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(E, 29) measured outputs y_sim (positions) and their rates (march.env.clf_outputs)."""
        return measured_outputs(
            self._env,
            self.robot,
            self.cfg.foot_sites,
            self.cfg.entity_name,
            self._root_body,
            self._upper_ids,
            self._masses(),
            self.stance_is_left,
            compiled=self.cfg.compile_math,
        )

    def stance_foot(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Stance foot site position (E, 3), linear velocity (E, 3) and angular velocity (E, 3)."""
        return stance_foot_state(
            self._env, self.cfg.foot_sites, self.cfg.entity_name, self.stance_is_left
        )

    @property
    def y_sim_pos(self) -> torch.Tensor:
        """(E, 29) measured outputs at the last refresh (computed when first asked for: the
        step itself only needs y_sim against V, in :meth:`clf_state`)."""
        if self._y_sim is None:
            self._y_sim = self.measured()
        return self._y_sim[0]

    @property
    def y_sim_vel(self) -> torch.Tensor:
        return self._y_sim[1] if self._y_sim is not None else (self.y_sim_pos, self._y_sim[1])[1]

    def _ref_key(self) -> tuple[int, int]:
        """Changes with the term's counter (updates, replans, resets) and with tau's version
        (any in-place write; an inference-mode tensor has none: the counter alone)."""
        version = -1 if self.tau.is_inference() else self.tau._version
        return (version, self._step_version)

    def _refresh_outputs(self) -> None:
        """y_ref at tau (the observation) and at tau + step_dt (the next step's V) in one
        reference call over both instants ((E, 2) times, no copy of the step state); y_sim on
        demand."""
        tau = torch.stack([self.tau, self.tau + self._env.step_dt], dim=-1)
        pos, vel = self.reference(tau)
        self.y_ref_pos, self.y_ref_vel = pos[:, 0], vel[:, 0]
        self._next_ref = (self._ref_key(), pos[:, 1], vel[:, 1])
        self._y_sim = None

    def clf_state(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(V, dV/dt, valid), each (E,), for the current env step; computed once per step.

        Called by the reward terms (before this step's command update): y_sim of the current
        physics state against y_ref at ``tau + step_dt``, then one ``VHistory.update``.
        """
        step = int(self._env.common_step_counter)
        if step != self._v_step:
            self._v_step = step
            cached = self._next_ref
            if cached is not None and cached[0] == self._ref_key():
                ref_pos, ref_vel = cached[1], cached[2]
            else:
                ref_pos, ref_vel = self.reference(self.tau + self._env.step_dt)
            sim_pos, sim_vel = self.measured()
            prod = self.clf.products_of_outputs(sim_pos, sim_vel, ref_pos, ref_vel, self.mask)
            self.v_products = prod  # each output's term of V, for march.env.clf_meter
            self.v = prod.sum(-1)
            self.vdot, self.v_valid = self.v_history.update(self.v)
        return self.v, self.vdot, self.v_valid

    # ---------------------------------------------------------------- observation

    def observation(self) -> torch.Tensor:
        """Privileged reference observation (E, 2*29 + 3N + 2), relative to the base (layout:
        :func:`march.env.clf_outputs.reference_in_base_frame`; the base's position and heading
        shared with the other observation terms: :func:`march.env.step_cache.root_frame`)."""
        return reference_in_base_frame(
            (self.y_ref_pos, self.y_ref_vel),
            self.plan_footholds,
            (self.tau, self.step.duration),
            root_frame(self._env, self.cfg.entity_name),
        )


def reference_term(env: ManagerBasedRlEnv, command_name: str = "reference") -> ReferenceCommand:
    term = env.command_manager.get_term(command_name)
    if not isinstance(term, ReferenceCommand):
        raise TypeError(f"command {command_name!r} is not a ReferenceCommand")
    return term
