"""The reference command's planner batch (march.env.replan_queue, issue 41): one of a few fixed
sizes, the resets first and never deferred, the due touchdowns / timeouts after them in env
order, nothing lost; checked against a plain model over many generated steps, and planted
faults make the check fail."""

import pytest
import torch

from march.env.replan_queue import ReplanBatch, ReplanQueue


def allowed_sizes(num_envs: int, capacity: int) -> set[int]:
    """The batch sizes the module docstring allows: capacity, powers of two above it, E."""
    cap = min(capacity, num_envs)
    sizes = {cap, num_envs}
    b = 1
    while b < num_envs:
        if b > cap:
            sizes.add(b)
        b *= 2
    return sizes


def run_queue(queue: ReplanQueue, steps: int, seed: int, flush: int) -> dict[str, int]:
    """Drive ``queue`` as the command term does (resets between updates, then take_resets and
    next_batch) with random resets (sometimes bursts beyond the capacity), touchdowns, timeouts
    and partial ``active`` masks, then ``flush`` updates without new events; assert every rule
    against a plain model of the waiting events. Returns counts the tests check are nonzero."""
    e, cap = queue.num_envs, queue.capacity
    sizes = allowed_sizes(e, cap)
    g = torch.Generator().manual_seed(seed)
    td = torch.zeros(e, dtype=torch.bool)  # model: a touchdown waits
    to = torch.zeros(e, dtype=torch.bool)  # model: a timeout waits (a touchdown outranks it)
    deferred = torch.zeros(e, dtype=torch.long)
    seen = {"big_batches": 0, "deferred": 0, "served": 0, "resets": 0}
    added = [torch.arange(e)]  # model: the envs reset since the last update (construction: all)
    for t in range(steps + flush):
        quiet = t >= steps
        u = float(torch.rand((), generator=g))
        p_new = 0 if quiet or u < 0.4 else (int(e * 0.9) if u > 0.95 else int(u * 6))
        if p_new:
            ids = torch.randperm(e, generator=g)[:p_new]
            queue.add_resets(ids)
            added.append(ids)
            if u > 0.8:  # a second reset call before the update (an env may be in both)
                more = torch.randperm(e, generator=g)[:3]
                queue.add_resets(more)
                added.append(more)
                td[more] = False
                to[more] = False
            td[ids] = False
            to[ids] = False
        resets = queue.take_resets()
        p = resets.numel()
        assert torch.equal(resets, torch.cat([torch.zeros(0, dtype=torch.long), *added])), (
            "every reset, in the next update"
        )
        added = []
        seen["resets"] += p
        running = ~queue.is_reset
        rate = 0.0 if quiet else 0.35
        touchdown = (torch.rand(e, generator=g) < rate) & running
        timeout = (torch.rand(e, generator=g) < rate / 3) & running
        if t % 7 == 3:  # mjlab's auto-reset path: only some envs active in this update
            active = torch.rand(e, generator=g) < 0.7
            touchdown &= active
            timeout &= active
        else:
            active = torch.ones(e, dtype=torch.bool)
        batch = queue.next_batch(touchdown, timeout, active)
        b = batch.ids.numel()
        # (p > E: an env reset twice between updates, e.g. at construction and the first
        # reset; planned p times over, identical rows)
        assert b in sizes or (p > e and b == p), (b, p, sizes)
        seen["big_batches"] += b > min(cap, e)
        assert batch.apply.shape == batch.ramp.shape == (b,)
        # The resets first, all of them, starting a ramped new step; never deferred.
        assert batch.num_resets == p
        assert torch.equal(batch.ids[:p], resets)
        assert batch.apply[:p].all() and batch.ramp[:p].all()
        assert not batch.ramp[p:].any()
        rest = batch.ids[p:]
        assert torch.equal(rest, batch.sel) and rest.unique().numel() == rest.numel()
        assert not queue.is_reset[rest].any()
        # The model: due envs, served in env order as far as the rows after the resets go.
        td |= touchdown
        to = (to | timeout) & ~td
        due = (td | to) & active
        expect = due.nonzero().flatten()[: b - p]
        served = torch.zeros(e, dtype=torch.bool)
        served[expect] = True
        assert torch.equal(rest[: expect.numel()], expect), "due envs first, in env order"
        assert torch.equal(batch.apply[p:], served[rest])
        assert torch.equal(batch.serve, served[rest])
        assert torch.equal(batch.flip, (served & td)[rest])
        deferred += due & ~served
        td &= ~served
        to &= ~served
        seen["deferred"] += int((due & ~served).sum())
        seen["served"] += int(served.sum())
        # Nothing lost: what the model still waits for, the queue does, counted per update.
        assert torch.equal(queue.waiting(), td | to)
        assert torch.equal(queue.deferred_count, deferred)
    assert not queue.waiting().any(), "every waiting event is served once events stop"
    return seen


@pytest.mark.parametrize("e,capacity", [(16, 8), (64, 8), (100, 13), (37, 5)])
def test_the_planner_batch_has_a_fixed_size_and_loses_nothing(e, capacity):
    seen = run_queue(ReplanQueue(e, capacity, "cpu"), steps=300, seed=e, flush=e)
    # The checks saw what they guard: bursts of resets, deferrals, service.
    assert seen["big_batches"] > 0 and seen["deferred"] > 0 and seen["served"] > 0


def test_batch_sizes_hand_computed():
    q = ReplanQueue(100, 13, "cpu")
    got = {p: q.batch_size(p) for p in (0, 1, 13, 14, 16, 17, 33, 64, 65, 100, 130)}
    assert got == {
        0: 13,
        1: 13,
        13: 13,
        14: 16,
        16: 16,
        17: 32,
        33: 64,
        64: 64,
        65: 100,
        100: 100,
        130: 130,
    }
    assert ReplanQueue(4, 8, "cpu").batch_size(0) == 4  # capacity beyond the envs


class _ResetsLast(ReplanQueue):
    """Planted fault: the resets appended after the running envs."""

    def next_batch(self, touchdown, timeout, active):
        b = super().next_batch(touchdown, timeout, active)
        p = b.num_resets
        roll = lambda x: torch.cat([x[p:], x[:p]])  # noqa: E731
        return b._replace(ids=roll(b.ids), apply=roll(b.apply), ramp=roll(b.ramp))


class _TruncatedResets(ReplanQueue):
    """Planted fault: at most ``capacity`` resets planned in an update (the rest dropped)."""

    def next_batch(self, touchdown, timeout, active):
        b = super().next_batch(touchdown, timeout, active)
        if b.num_resets <= self.capacity:
            return b
        keep = torch.ones_like(b.apply)
        keep[self.capacity : b.num_resets] = False
        cut = lambda x: x[keep]  # noqa: E731
        return ReplanBatch(
            cut(b.ids), cut(b.apply), cut(b.ramp), self.capacity, b.sel, b.serve, b.flip
        )


class _GrowingBatch(ReplanQueue):
    """Planted fault: the old rule, p resets plus a full capacity of running envs (a new shape
    on every reset step)."""

    def batch_size(self, num_resets):
        return min(self.num_envs, num_resets + self.capacity)


class _LateResets(ReplanQueue):
    """Planted fault: a reset waits for an update without other resets."""

    def take_resets(self):
        if len(self._resets) > 1:
            self._resets, later = self._resets[:1], self._resets[1:]
            out = super().take_resets()
            self._resets = later
            return out
        return super().take_resets()


@pytest.mark.parametrize("fault", [_ResetsLast, _TruncatedResets, _GrowingBatch, _LateResets])
def test_a_planted_fault_fails_the_check(fault):
    with pytest.raises(AssertionError):
        run_queue(fault(16, 8, "cpu"), steps=300, seed=16, flush=16)


@pytest.mark.sim
def test_the_teacher_env_plans_only_the_allowed_batch_sizes(monkeypatch):
    """In a clf teacher env under random actions (falls reset envs, steps touch down), every
    planner call of the reference command has one of the allowed sizes (the first update after
    the construction-time plan may hold each env twice: it is reset by both)."""
    from march.config.cli import load
    from march.env import reference_command
    from march.env.build import make_env

    sizes: list[int] = []
    plan = reference_command.plan_footsteps

    def recording(stance_xy, *args, **kwargs):
        sizes.append(stance_xy.shape[0])
        return plan(stance_xy, *args, **kwargs)

    monkeypatch.setattr(reference_command, "plan_footsteps", recording)
    # 16 envs, capacity 8 (smoke's 4 envs would make the capacity every env: one size anyway;
    # measured here: 31 resets, 43 replans of running envs, every call 8 rows, and with the
    # old rule, p resets + 8, sizes 8-11)
    env = make_env(load(["compute=smoke", "reward=clf", "compute.num_envs=16"]), "teacher")
    try:
        term = env.command_manager.get_term("reference")
        e, cap = env.num_envs, term.queue.capacity
        n_act = env.action_manager.total_action_dim
        g = torch.Generator().manual_seed(0)
        env.reset()
        first = len(sizes)
        resets = 0
        for _ in range(80):
            _, _, terminated, truncated, _ = env.step(2.0 * torch.randn(e, n_act, generator=g))
            resets += int((terminated | truncated).sum())
        touchdowns = int((term.touchdown_count + term.forced_count).sum())
    finally:
        env.close()
    assert cap < e, "a batch of every env would prove nothing"
    assert resets > 0 and touchdowns > 0, "the run must reset envs and replan running ones"
    allowed = allowed_sizes(e, cap)
    assert set(sizes[first:]) <= allowed, (sorted(set(sizes[first:])), allowed)
    assert all(s in allowed or e < s <= 2 * e for s in sizes[:first])
