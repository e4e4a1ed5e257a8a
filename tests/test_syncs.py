"""No host synchronisation in march's per-step code (issue 11).

A host sync is a tensor operation that makes the CPU wait for the device: reading a value
(``.item()``, ``int()`` / ``float()`` / ``bool()`` of a tensor, e.g. ``if mask.any():``), moving
data to the host (``.cpu()``, ``.tolist()``, ``.numpy()``) or producing a tensor whose size depends
on the data (``.nonzero()``, single-argument ``torch.where``, boolean-mask indexing and assignment,
``masked_select``, ``unique``). On CPU they cost nothing, on a GPU each one stalls the stream, so
they are counted here on CPU, where the suite runs: :class:`SyncCounter` (a
``torch.overrides.TorchFunctionMode``) sees every torch call and records those issued from a file
under ``march/`` (the first frame outside torch's own package decides; mjlab's own syncs, e.g.
its ``len(reset_env_ids)``, are not march's to remove; a wrapper another module bound in torch's
place, whatever was imported first, only passes a call on). ``len()`` of a tensor is not counted: the
shape is known on the host; the ``nonzero()`` that made a data-dependent shape is.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from types import FunctionType

import pytest
import torch
from torch.overrides import TorchFunctionMode

ROOT = Path(__file__).resolve().parent.parent
MARCH_DIR = str(ROOT / "march") + "/"
TESTS_DIR = str(ROOT / "tests") + "/"
ENV_FILE = "mjlab/envs/manager_based_rl_env.py"
WARP_WRAP = "warp/_src/torch.py"
"""``warp.to_torch`` wraps a warp array's memory with ``torch.as_tensor`` (the array interface:
no copy), which is not a host-to-device copy."""
TRANSPARENT = {"scoped": "march/env/step_cache.py"}
"""March wrappers that only pass a call through (step_cache's per-compute scope around mjlab's
reward and observation managers): a sync inside an mjlab term they call is not march's."""

ALWAYS_SYNC = {
    "item",
    "__bool__",
    "__int__",
    "__float__",
    "__index__",
    "nonzero",
    "argwhere",
    "cpu",
    "tolist",
    "numpy",
    "masked_select",
    "unique",
    "unique_consecutive",
    "repeat_interleave",
}
"""Torch functions / tensor methods that always wait for the device's result."""


HOST_DATA = {"tensor", "as_tensor", "asarray"}
"""Factories that build a tensor from host data (a list, a number, a numpy array): on a GPU each
is a blocking host-to-device copy (``torch.from_numpy`` does not reach a ``TorchFunctionMode``)."""


def _items(index: object) -> tuple:
    return index if isinstance(index, tuple) else (index,)


def _has_bool_index(index: object) -> bool:
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in _items(index))


def _has_host_index(index: object) -> bool:
    """A list or numpy array as an index: torch copies it to the device first."""
    return any(isinstance(i, list) or type(i).__module__ == "numpy" for i in _items(index))


def sync_kind(func: object, args: tuple, name: str | None = None) -> str | None:
    """The kind of host sync ``func(*args)`` causes (``h2d ...``: a host-to-device copy of data
    made on the host), or None. ``name``: the torch name ``func`` is bound under, where that is
    not its own ``__name__`` (a wrapper bound in torch's place)."""
    name = name or getattr(func, "__name__", "")
    if name in ALWAYS_SYNC:
        if name == "repeat_interleave" and not any(isinstance(a, torch.Tensor) for a in args[1:2]):
            return None  # an int repeat count has a host-known size
        return name
    if name == "where" and len(args) == 1:
        return "where(cond)"
    if name in HOST_DATA and args and not isinstance(args[0], torch.Tensor):
        return f"h2d {name}"
    if name in ("__getitem__", "__setitem__") and len(args) >= 2:
        if _has_bool_index(args[1]):
            return f"{name}[bool mask]"
        if _has_host_index(args[1]):
            return f"h2d {name}[host index]"
    return None


def _march_cause(frame: object) -> str | None:
    """Where march is behind a call: the innermost frame in a ``march/`` file, or a method of a
    class defined in march (an mjlab method a march term inherits), up to the caller's frame."""
    while frame is not None:
        name = frame.f_code.co_filename
        if name.endswith(ENV_FILE):
            return None  # mjlab's env step / reset itself: what called it is not the cause
        if name.startswith(MARCH_DIR) and not name.endswith(
            TRANSPARENT.get(frame.f_code.co_name, "?")
        ):
            return f"{name[len(str(ROOT)) + 1 :]}:{frame.f_lineno}"
        if name.startswith(TESTS_DIR):
            return None
        owner = frame.f_locals.get("self")
        if owner is not None and type(owner).__module__.startswith("march."):
            return f"{type(owner).__name__} ({Path(name).name}:{frame.f_lineno})"
        frame = frame.f_back
    return None


def _in_torch(frame: object) -> bool:
    """A frame of torch's own code, known by its module's name (``torch``, ``torch.*``): a file
    path would miss torch reached through another path (a symlinked ``lib64``, a copy)."""
    module = frame.f_globals.get("__name__") or ""
    return module == "torch" or module.startswith("torch.")


def _rebound_wrappers() -> dict[object, str]:
    """The code of every function some other module has bound in place of a torch function or
    tensor method a sync can come from (``torch.Tensor.unique = wrap(torch.Tensor.unique)``, at
    import, by whatever was imported first), and of what such a wrapper wraps in turn. A call from
    march goes through the wrapper into torch: the wrapper only passes it on, and the sync is
    still the caller's (it was missed: "Right contains one more item: 'unique'"). Each wrapper
    maps to the torch name it stands for: torch's C methods hand a mode the function bound under
    their name now, the wrapper, whatever its own ``__name__``."""
    names = ALWAYS_SYNC | HOST_DATA | {"where", "__getitem__", "__setitem__"}
    todo = [(getattr(owner, n, None), n) for owner in (torch, torch.Tensor) for n in names]
    found: dict[object, str] = {}
    while todo:
        f, name = todo.pop()
        code = getattr(f, "__code__", None)
        if code is None or f in found:
            continue  # a builtin: torch's own C function or method
        module = getattr(f, "__globals__", {}).get("__name__") or ""
        if module == "torch" or module.startswith("torch."):
            continue  # torch's own Python function (functools.wraps copies __module__, not this)
        found[f] = name
        todo.append((getattr(f, "__wrapped__", None), name))
        todo += [(c.cell_contents, name) for c in f.__closure__ or () if callable(c.cell_contents)]
    return found


class SyncCounter(TorchFunctionMode):
    """Records every host sync: ``hits`` those issued from a line of march's own modules
    (``root``), ``every`` all of them as ``(kind, file:line, march cause or None)``. The caller is
    the first frame outside torch and outside any wrapper another module bound in place of a
    torch function (read when the counter starts, so whatever was imported first is seen)."""

    def __init__(self, root: str = MARCH_DIR) -> None:
        super().__init__()
        self.root = root
        self.hits: list[tuple[str, str]] = []
        self.every: list[tuple[str, str, str | None]] = []
        self.rebound: dict[object, str] = {}  # wrapper function -> the torch name it stands for
        self.pass_through: set[object] = set()  # their code: frames that only pass a call on

    def __enter__(self):
        self.rebound = _rebound_wrappers()
        self.pass_through = {f.__code__ for f in self.rebound}
        return super().__enter__()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = self.rebound.get(func) if isinstance(func, FunctionType) else None
        kind = sync_kind(func, args, name)
        if kind is not None:
            frame = sys._getframe(1)
            while frame is not None and (_in_torch(frame) or frame.f_code in self.pass_through):
                frame = frame.f_back
            if frame is not None and not (kind.startswith("h2d") and WARP_WRAP in name_of(frame)):
                name = frame.f_code.co_filename
                where = f"{_short(name)}:{frame.f_lineno}"
                self.every.append((kind, where, _march_cause(frame)))
                if name.startswith(self.root):
                    self.hits.append((kind, f"{name[len(str(ROOT)) + 1 :]}:{frame.f_lineno}"))
        return func(*args, **(kwargs or {}))

    def march_caused(self) -> list[tuple[str, str, str | None]]:
        return [h for h in self.every if h[2] is not None]


def name_of(frame: object) -> str:
    return frame.f_code.co_filename


def _short(filename: str) -> str:
    """A file name relative to the repository or to site-packages."""
    if filename.startswith(str(ROOT)):
        return filename[len(str(ROOT)) + 1 :]
    _, _, rest = filename.partition("site-packages/")
    return rest or filename


SYNCING_SNIPPET = """
x = torch.arange(6.0)
m = x > 2.0
x.sum().item()
bool(m.any())
if m.all():
    pass
int(x.max())
float(x.mean())
m.nonzero()
torch.where(m)
x.cpu()
x.tolist()
x[m]
x[m] = 0.0
x.unique()
"""
SYNCING_KINDS = [
    "item",
    "__bool__",
    "__bool__",
    "__int__",
    "__float__",
    "nonzero",
    "where(cond)",
    "cpu",
    "tolist",
    "__getitem__[bool mask]",
    "__setitem__[bool mask]",
    "unique",
]

SYNC_FREE_SNIPPET = """
x = torch.arange(6.0)
m = x > 2.0
ids = torch.arange(3)
y = torch.where(m, x, torch.zeros_like(x))
y = x.masked_fill(~m, 0.0)
y = x[ids]
x[ids] = 1.0
x.index_copy_(0, ids, torch.ones(3))
n = len(x)
s = x.sum() * m.any()
"""


def _run(snippet: str, filename: str) -> list[tuple[str, str]]:
    code = compile(snippet, filename, "exec")
    with SyncCounter() as counter:
        exec(code, {"torch": torch})
    return counter.hits


def test_counter_sees_every_sync_kind_issued_from_march():
    hits = _run(SYNCING_SNIPPET, MARCH_DIR + "example.py")
    assert [k for k, _ in hits] == SYNCING_KINDS
    assert all(where.startswith("march/example.py:") for _, where in hits)


def _pass_on(f):
    """A wrapper as a library binds one in place of a torch function (a compat shim, a
    deprecation notice): it only passes the call on."""

    @functools.wraps(f)
    def wrapper(*args, **kwargs):
        return f(*args, **kwargs)

    return wrapper


def _pass_on_plain(f):
    return lambda *args, **kwargs: f(*args, **kwargs)  # no __wrapped__: found in its closure


@pytest.mark.parametrize("layers", [1, 2])
def test_counter_sees_syncs_through_what_an_earlier_import_bound_in_torchs_place(
    monkeypatch, layers
):
    """The order-dependent failure ("Right contains one more item: 'unique'"): a module imported
    earlier in the same process had bound a wrapper in place of ``torch.Tensor.unique``, so the
    first frame outside torch was the wrapper's, and march's ``x.unique()`` was not counted."""
    for owner, name in [(torch.Tensor, "unique"), (torch, "unique"), (torch.Tensor, "item")]:
        f = getattr(owner, name)
        for _ in range(layers):
            f = _pass_on(f) if layers == 1 else _pass_on_plain(_pass_on(f))
        monkeypatch.setattr(owner, name, f)
    assert torch.Tensor.unique.__code__.co_filename == __file__  # bound from outside torch
    hits = _run(SYNCING_SNIPPET, MARCH_DIR + "example.py")
    assert [k for k, _ in hits] == SYNCING_KINDS
    assert all(where.startswith("march/example.py:") for _, where in hits)
    assert _run(SYNCING_SNIPPET, str(ROOT / "tests" / "example.py")) == []
    with SyncCounter() as counter:
        torch.unique(torch.arange(3))  # from this file, through the wrapper: not march's
    assert counter.hits == [] and [k for k, _, _ in counter.every] == ["unique"]


def test_counter_ignores_other_files_and_sync_free_ops():
    assert _run(SYNCING_SNIPPET, str(ROOT / "tests" / "example.py")) == []
    assert _run(SYNC_FREE_SNIPPET, MARCH_DIR + "example.py") == []


def test_episode_stats_step_has_no_sync_and_keeps_the_last_window():
    from march.learn.teacher import EpisodeStats

    stats = EpisodeStats(num_envs=4, device="cpu", window=3)
    reward = torch.tensor([1.0, 2.0, 3.0, 4.0])
    progress = torch.tensor([0.5, 1.0, 1.5, 2.0])
    none = torch.zeros(4, dtype=torch.bool)
    with SyncCounter() as counter:
        stats.step(reward, none, progress)  # nothing ends
        stats.step(reward, torch.tensor([True, False, False, True]), progress)
        # env 0 and 3 ended after 2 steps: returns 2, 8; lengths 2, 2; distances 0.5, 2.0
        stats.step(reward, torch.tensor([True, True, True, False]), progress)
        # env 0 (1 step: 1), env 1 (3 steps: 6), env 2 (3 steps: 9); window 3 keeps the last 3
        # episodes in env order: env 0 (1), env 1 (6), env 2 (9)
    assert counter.hits == []
    out = stats.pop()
    assert out["mean_reward"] == pytest.approx((1.0 + 6.0 + 9.0) / 3)
    assert out["mean_episode_length"] == pytest.approx((1 + 3 + 3) / 3)
    assert out["mean_distance_m"] == pytest.approx((0.5 + 1.0 + 1.5) / 3)


def test_episode_stats_window_over_many_random_steps():
    """Against a plain Python list of finished episodes (env order within a step)."""
    from march.learn.teacher import EpisodeStats

    gen = torch.Generator().manual_seed(3)
    for window in (1, 5, 40):
        stats = EpisodeStats(num_envs=16, device="cpu", window=window)
        ret, length, ended = [0.0] * 16, [0] * 16, []
        for _ in range(60):
            reward = torch.rand(16, generator=gen)
            done = torch.rand(16, generator=gen) < 0.3
            progress = torch.rand(16, generator=gen)
            stats.step(reward, done, progress)
            for e in range(16):
                ret[e] += float(reward[e])
                length[e] += 1
                if done[e]:
                    ended.append((ret[e], length[e], float(progress[e])))
                    ret[e], length[e] = 0.0, 0
        last = ended[-window:]
        out = stats.pop()
        assert out["mean_reward"] == pytest.approx(sum(r for r, _, _ in last) / len(last), rel=1e-5)
        assert out["mean_episode_length"] == pytest.approx(sum(n for _, n, _ in last) / len(last))
        assert out["mean_distance_m"] == pytest.approx(sum(d for _, _, d in last) / len(last))
    empty = EpisodeStats(num_envs=2, device="cpu").pop()
    assert all(v != v for v in empty.values())  # NaN until an episode ends


# ---------------------------------------------------------------------------------- real env


def _count_env_steps(env, steps: int) -> dict[str, object]:
    """Host syncs of ``steps`` env steps (random actions, then zeros) after a reset and one
    step outside the count (lazy first-use set-ups); ``per_step``: each step's syncs apart."""
    gen = torch.Generator().manual_seed(0)
    shape = (env.num_envs, env.action_manager.total_action_dim)
    env.reset()
    env.step(torch.zeros(shape))
    resets = torch.zeros((), dtype=torch.long)
    per_step: list[list[tuple[str, str, str | None]]] = []
    with torch.no_grad(), SyncCounter() as counter:
        for i in range(steps):
            # random actions (falls, resets, replans), then zeros (standing, touchdowns)
            a = 2 * torch.rand(shape, generator=gen) - 1 if i < steps // 2 else torch.zeros(shape)
            n = len(counter.every)
            _, _, terminated, truncated, _ = env.step(a)
            per_step.append(counter.every[n:])
            resets += (terminated | truncated).sum()
    return {"counter": counter, "resets": int(resets), "per_step": per_step}


def _steps_without_sync(reward: str, steps: int) -> dict[str, object]:
    from march.config.cli import load
    from march.env.build import make_env

    cfg = load(["compute=smoke", f"reward={reward}", "dr=paper", "compute.num_envs=8"])
    env = make_env(cfg, "teacher")
    try:
        out = _count_env_steps(env, steps)
        if reward == "clf":
            out["replans"] = int(env.command_manager.get_term("reference").replan_count.sum())
        return out
    finally:
        env.close()


STEPS = 60


@pytest.fixture(scope="module")
def rough_syncs() -> int:
    """Host syncs of mjlab's bare rough G1 over the same steps (8 envs)."""
    from march.env.build import bare_env

    env = bare_env("Mjlab-Velocity-Rough-Unitree-G1", 8, 0, "cpu")
    try:
        return len(_count_env_steps(env, STEPS)["counter"].every)
    finally:
        env.close()


@pytest.fixture(scope="module")
def clf_syncs() -> dict[str, object]:
    """The clf teacher env's (dr=paper, 8 envs) syncs over ``STEPS`` steps, in total and per
    step: both tests of the clf env read this one run (each had built the env and stepped it
    the same way itself, the same seed and actions)."""
    return _steps_without_sync("clf", steps=STEPS)


@pytest.mark.sim
@pytest.mark.parametrize("reward", ["clf", "modelfree"])
def test_env_steps_issue_no_host_sync_from_march(reward, rough_syncs, request):
    """Counted over every file: march's step syncs no more than bare rough's, and nothing that
    syncs is march's (its code, or an mjlab method a march term inherits)."""
    if reward == "clf":
        out = request.getfixturevalue("clf_syncs")
    else:
        out = _steps_without_sync(reward, steps=STEPS)
    counter = out["counter"]
    assert out["resets"] > 0  # the reset path (curriculum, DR events, replans) ran
    if reward == "clf":
        assert out["replans"] > 8  # more plans than the initial ones: resets, touchdowns
    hits = counter.hits
    assert hits == [], f"{len(hits)} host syncs from march: {sorted(set(hits))[:20]}"
    caused = counter.march_caused()
    assert caused == [], f"{len(caused)} host syncs caused by march: {sorted(set(caused))[:20]}"
    assert 0 < len(counter.every) <= rough_syncs, (len(counter.every), rough_syncs)


def test_counter_traces_inherited_methods_and_host_data_to_march():
    """A sync in a method a march class inherits is march's; a host list as an index or a
    tensor made from host data is a host-to-device copy."""
    ns: dict = {"torch": torch}
    exec(
        compile("class Base:\n def f(self, x):\n  return x.nonzero()\n", "/lib/base.py", "exec"), ns
    )
    Derived = type("Derived", (ns["Base"],), {"__module__": "march.example"})
    x = torch.arange(4.0)
    with SyncCounter() as counter:
        Derived().f(x)
        ns["Base"]().f(x)
        exec(
            compile("x[[0, 1]]\ntorch.tensor([1.0])\nx[torch.arange(2)]", "/lib/h.py", "exec"),
            {"torch": torch, "x": x},
        )
    kinds = [(k, m is not None) for k, _, m in counter.every]
    assert kinds == [
        ("nonzero", True),
        ("nonzero", False),
        ("h2d __getitem__[host index]", False),
        ("h2d tensor", False),
    ]
    assert counter.every[0][2].startswith("Derived (base.py:")


@pytest.mark.sim
def test_runners_per_step_code_issues_no_host_sync(tmp_path, monkeypatch):
    """One teacher iteration's rollout and one distillation rollout: every host sync there is
    mjlab's own (none traced to the runners, their fault handling, or a march term)."""
    from march.config.cli import load
    from march.env.build import make_env
    from march.learn.distill import DistillRunner
    from march.learn.metrics import MetricsLog
    from march.learn.teacher import TeacherRunner

    cfg = load(["compute=smoke", "compute.num_envs=8"])
    env = make_env(cfg, "teacher")
    log = MetricsLog(tmp_path, cfg.logger, "t")
    try:
        runner = TeacherRunner(env, cfg, tmp_path, log)
        counter = SyncCounter()
        seen: dict[str, int] = {}
        real_returns = runner.alg.compute_returns

        def compute_returns(obs):  # the rollout ends here; the update may read values
            seen.setdefault("rollout", len(counter.every))
            return real_returns(obs)

        monkeypatch.setattr(runner.alg, "compute_returns", compute_returns)
        with counter:
            runner.learn(1)
        rollout = counter.every[: seen["rollout"]]
        caused = [h for h in rollout if h[2] is not None]
        assert caused == [], f"teacher rollout: {sorted(set(caused))[:20]}"
        assert len(rollout) >= cfg.teacher.num_steps_per_env  # mjlab's own, counted
        teacher_payload = runner.payload()
    finally:
        log.close()
        env.close()
    env = make_env(cfg, "student")
    log = MetricsLog(tmp_path / "s", cfg.logger, "s")
    try:
        runner = DistillRunner(env, cfg, tmp_path / "s", log, teacher_payload, "teacher.pt")
        from march.learn.teacher import EpisodeStats

        stats = EpisodeStats(env.num_envs, cfg.compute.device)
        with SyncCounter() as counter:
            _, reward = runner._rollout(stats)
        caused = counter.march_caused()
        assert caused == [], f"distillation rollout: {sorted(set(caused))[:20]}"
        assert torch.isfinite(reward)  # the mean reward, on the device until the row is written
    finally:
        log.close()
        env.close()


@pytest.mark.sim
def test_fault_resets_count_once_and_leave_finite_rows():
    """A NaN in the physics state is reset in the same step by the ``nonfinite`` termination; a
    NaN in an observation is zeroed now and the env reset at the next step; each counted once."""
    import math

    from march.config.cli import load
    from march.env.build import make_env
    from march.learn.faults import EnvFaults

    cfg = load(["compute=smoke", "reward=modelfree", "compute.num_envs=4"])
    env = make_env(cfg, "teacher")
    try:
        faults = EnvFaults(env)
        zeros = torch.zeros(env.num_envs, env.action_manager.total_action_dim)
        env.reset()
        with torch.no_grad():
            env.episode_length_buf[:] = 3
            env.sim.data.qpos[1, 2] = math.nan
            obs, reward, term, _, _ = env.step(zeros)
            obs["actor"][2, 0] = math.nan
            bad = faults.after_step(obs, reward, None)
            assert bad.tolist() == [False, True, True, False]
            assert bool(term[1]) and not bool(term[2])  # env 2 is ended by the runner only
            assert int(env.episode_length_buf[1]) == 0  # reset in this step
            assert float(obs["actor"][2].abs().sum()) == 0.0 and float(reward[1]) == 0.0
            obs, reward, term, _, _ = env.step(zeros)
            bad = faults.after_step(obs, reward, None)
            assert bad.tolist() == [False, False, False, False]
            assert term.tolist() == [False, False, True, False]  # the pending reset
            assert int(env.episode_length_buf[2]) == 0
            assert torch.isfinite(env.sim.data.qpos).all()
        assert faults.pop() == 2 and faults.pop() == 0
        # march's upright and foot_slip equal mjlab's (index kept on the device)
        from mjlab.managers.reward_manager import RewardTermCfg
        from mjlab.managers.scene_entity_config import SceneEntityCfg
        from mjlab.tasks.velocity import mdp as vel_mdp

        from march.env.rewards import foot_slip, upright

        torso = SceneEntityCfg("robot", body_names=("torso_link",))
        feet = SceneEntityCfg("robot", site_names=("left_foot", "right_foot"))
        torso.resolve(env.scene)
        feet.resolve(env.scene)
        gen = torch.Generator().manual_seed(1)
        mj_upright = vel_mdp.upright(RewardTermCfg(func=vel_mdp.upright, weight=1.0), env)
        for _ in range(6):
            env.step(2 * torch.rand(zeros.shape, generator=gen) - 1)
            want = mj_upright(env, std=0.5, asset_cfg=torso)
            assert torch.allclose(upright(env, 0.5, ("torso_link",)), want, atol=1e-6)
            want = -vel_mdp.feet_slip(env, "feet_ground_contact", "twist", 0.05, feet)
            got = foot_slip(env, "feet_ground_contact", "twist", 0.05, ("left_foot", "right_foot"))
            assert torch.allclose(got, want, atol=1e-6)
    finally:
        env.close()


# ------------------------------------------------- issue 41: syncs left to mjlab's reset selection

MAX_SYNCS_PER_STEP = 2
"""What a teacher env step may still sync (issue 41): mjlab's own reset selection
(``reset_buf.nonzero()`` in ``ManagerBasedRlEnv.step``); every term march chooses is sync-free:
the twist command (march.env.velocity_command), the push (march.env.push_event), the
termination counts and curriculum state on reset (march.env.reset_extras)."""
MJLAB_DR = ("mjlab/envs/mdp/dr/", "mjlab/envs/mdp/events.py")
"""Where the host-to-device copies of a reset step come from: mjlab's DR and reset event
functions build their range tensors from Python numbers on every call (not removed yet)."""


@pytest.mark.sim
def test_a_teacher_env_step_syncs_at_most_twice(rough_syncs, clf_syncs):
    """Every call that waits for the device (``.item()``, ``nonzero()``, ``bool()``...) in
    ``STEPS`` clf teacher env steps with dr=paper (random actions with falls and resets, then
    zeros), in any file: at most 2 per step, in every step (counted per step, reset steps
    included), all in mjlab's env step itself; fewer than bare rough's. The host-to-device
    copies (reset steps only) all come from mjlab's DR / reset event functions."""
    per_step = clf_syncs["per_step"]
    assert clf_syncs["resets"] > 0 and len(per_step) == STEPS
    waits = [[h for h in hits if not h[0].startswith("h2d")] for hits in per_step]
    worst = max(len(w) for w in waits)
    lines = sorted({(k, w) for hits in waits for k, w, _ in hits})
    assert worst <= MAX_SYNCS_PER_STEP, (worst, lines)
    assert all("mjlab/envs/manager_based_rl_env.py:" in w for _, w in lines), lines
    copies = sorted({w for hits in per_step for k, w, _ in hits if k.startswith("h2d")})
    assert all(any(m in w for m in MJLAB_DR) for w in copies), copies
    assert sum(len(w) for w in waits) < rough_syncs
