"""Stepping-stone courses as pure data: the course geometry config and its layouts (numpy).

No simulator import: ``march.env.stone_terrain`` turns a :class:`CourseLayout` into MuJoCo box
geoms, and ``march.world.footholds`` turns layouts into the foothold tensors (``FootholdTable``,
the per-(level, column) ground truth the command term indexes).

Frames and conventions
- A layout lives in its sub-terrain's local frame: x in [0, size[0]] along the course, y in
  [0, size[1]] across it, z = 0 at the top of the start platform. mjlab's TerrainGenerator
  shifts the whole sub-terrain by the corner of its grid cell (no rotation), so world = local +
  corner, and the spawn point ``origin`` lands in ``TerrainEntity.terrain_origins[row, col]``.
- Every box is axis-aligned; ``center`` is the centre of its *top face*; every box extends from
  its top down to ``bottom`` (the top of the pit floor), so a foot that misses a stone falls
  ``cfg.pit_depth`` below the platform top.
- Entries are in course order: index 0 the start platform, then the stones (a side-by-side pair is
  two consecutive entries with the same ``step``), last the goal platform. The flat layout
  (curriculum=flat_first) is a single platform covering the whole sub-terrain: its index 0 is
  both start and goal, and its ``goal_distance`` / ``course_length`` are those of a stone course
  (where the goal platform would begin / end), so progress and success read the same on both.

Difficulty d in [0, 1] interpolates linearly between the ``*_easy`` and ``*_hard`` fields; a
range field is interpolated end by end, and each stone draws uniformly inside the interpolated
range (see :func:`difficulty_ranges`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from march.errors import ConfigError

ROLE_START = 0
"""``CourseLayout.role``: the start platform (also the single platform of the flat layout)."""
ROLE_STONE = 1
"""``CourseLayout.role``: a single stepping stone."""
ROLE_PAIR = 2
"""``CourseLayout.role``: one stone of a side-by-side pair (left/right choice)."""
ROLE_GOAL = 3
"""``CourseLayout.role``: the goal platform."""

Range = tuple[float, float]


@dataclass
class CourseCfg:
    """Geometry of one stepping-stone course (one mjlab sub-terrain). Lengths in metres."""

    size: tuple[float, float] = (12.0, 4.0)
    """Sub-terrain extent (x along the course, y across) [m]; mjlab's TerrainGeneratorCfg.size."""
    end_margin: float = 0.25
    """Pit between the sub-terrain's x-edges and the platforms, so consecutive levels (rows,
    placed end to end along x) are separated by a 2*end_margin gap [m]."""
    start_length: float = 1.5
    """Start platform length along x [m]; the spawn point is its centre."""
    goal_length: float = 1.5
    """Minimum goal platform length along x [m]; the goal platform runs from one gap after the
    last stone to ``size[0] - end_margin`` (so it is goal_length to goal_length + one pitch)."""
    platform_width: float = 2.0
    """Start and goal platform width along y [m]."""
    stone_size_easy: Range = (0.45, 0.50)
    """Stone side length range (x and y drawn independently) at difficulty 0 [m]."""
    stone_size_hard: Range = (0.25, 0.30)
    """Stone side length range at difficulty 1 [m]."""
    gap_easy: Range = (0.10, 0.15)
    """Gap along x between consecutive footholds (platform edges included) at difficulty 0 [m]."""
    gap_hard: Range = (0.35, 0.45)
    """Gap along x at difficulty 1 [m]."""
    height_easy: float = 0.0
    """Stone top height variation at difficulty 0: top z ~ U(-h, h) around the platform top [m]."""
    height_hard: float = 0.10
    """Stone top height variation at difficulty 1 [m]."""
    lateral_easy: Range = (0.0, 0.0)
    """Zig-zag amplitude at difficulty 0: stone k's centre is at y_mid + s_k * U(range), with
    s_k = +1/-1 alternating from a random first side [m]."""
    lateral_hard: Range = (0.10, 0.21)
    """Zig-zag amplitude at difficulty 1 [m]."""
    pair_prob: float = 0.2
    """Probability that a course step is a side-by-side pair (two stones at the same x, centred
    on the course axis) instead of a single stone: the robot must choose left or right."""
    pair_gap: Range = (0.10, 0.20)
    """Lateral gap between the two stones of a pair [m]."""
    max_stones: int = 24
    """Cap on the number of course steps (a pair counts once); by default the stones fill the
    corridor between the platforms, which takes 11-14 steps in a 12 m sub-terrain."""
    pit_depth: float = 1.0
    """Depth of the pit floor below the platform top [m]: every box extends down to -pit_depth."""
    hardware_stone_size: tuple[float, float] = (0.30, 0.30)
    """Hardware course: stone extent (x, y) [m] (paper: 4 stones, same height as the platforms)."""
    hardware_gaps: tuple[float, ...] = (0.25, 0.30, 0.25, 0.30, 0.25)
    """Hardware course: the 5 gaps along x (start->s1, s1->s2, s2->s3, s3->s4, s4->goal) [m]."""
    hardware_lateral: tuple[float, ...] = (0.12, -0.12, 0.12, -0.12)
    """Hardware course: lateral offset of the 4 stones from the course axis, alternating
    left (+y) / right (-y) [m]."""

    def __post_init__(self) -> None:
        problem = self._problem()
        if problem is not None:
            raise ConfigError(f"terrain.{problem}")

    def _problem(self) -> str | None:
        """The first value outside its domain, as ``key=value must be ...``, or None."""
        import math

        def fmt(v: object) -> str:
            return f"[{', '.join(str(x) for x in v)}]" if isinstance(v, (list, tuple)) else str(v)

        pairs = ("size", "stone_size_easy", "stone_size_hard", "gap_easy", "gap_hard")
        pairs += ("lateral_easy", "lateral_hard", "pair_gap", "hardware_stone_size")
        for key, value in vars(self).items():
            values = list(value) if isinstance(value, (list, tuple)) else [value]
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                return f"{key}={fmt(value)} must hold finite numbers"
            if key in pairs and len(values) != 2:
                return f"{key}={fmt(value)} must have 2 values"
        for key in ("end_margin", "height_easy", "height_hard"):
            if getattr(self, key) < 0:
                return f"{key}={getattr(self, key)} must be >= 0"
        for key in ("start_length", "goal_length", "platform_width", "pit_depth"):
            if not getattr(self, key) > 0:
                return f"{key}={getattr(self, key)} must be > 0"
        if self.max_stones < 1:
            return f"max_stones={self.max_stones} must be >= 1"
        if not 0.0 <= self.pair_prob <= 1.0:
            return f"pair_prob={self.pair_prob} must be a probability in [0, 1]"
        # Ranges [lo, hi] with lo <= hi; sizes strictly positive, gaps and amplitudes >= 0.
        for key in pairs:
            lo, hi = getattr(self, key)
            positive = key in ("size", "stone_size_easy", "stone_size_hard", "hardware_stone_size")
            if key not in ("size", "hardware_stone_size") and lo > hi:
                return f"{key}={fmt((lo, hi))} must be [lo, hi] with lo <= hi"
            if (positive and not min(lo, hi) > 0) or (not positive and min(lo, hi) < 0):
                return f"{key}={fmt((lo, hi))} must be {'> 0' if positive else '>= 0'}"
        if any(g < 0 for g in self.hardware_gaps):
            return f"hardware_gaps={fmt(self.hardware_gaps)} must be >= 0"
        if len(self.hardware_gaps) != len(self.hardware_lateral) + 1:
            return (
                f"hardware_gaps={fmt(self.hardware_gaps)} and terrain.hardware_lateral="
                f"{fmt(self.hardware_lateral)}: hardware_gaps must have one entry more (a gap "
                "before each stone and one before the goal)"
            )
        if self.size[1] < self.platform_width:
            return (
                f"platform_width={self.platform_width} must be <= the sub-terrain's width, "
                f"size[1] of terrain.size={fmt(self.size)}"
            )
        # The goal platform needs some length even when not one stone fits.
        need = 2 * self.end_margin + self.start_length + max(self.gap_easy[1], self.gap_hard[1])
        if not self.size[0] > need:
            return (
                f"size={fmt(self.size)}: the length size[0] must be > {need:.3g} (2 end_margin"
                " + start_length + the largest gap, so the goal platform has room)"
            )
        return None

    @property
    def spawn_x(self) -> float:
        """x of the spawn point (start platform centre) in the sub-terrain frame [m]."""
        return self.end_margin + 0.5 * self.start_length

    @property
    def goal_distance_max(self) -> float:
        """Worst case over every difficulty and seed of a course's ``goal_distance`` [m].

        :func:`generate_course` adds a stone only while one more maximal gap and the minimum
        goal platform still fit, so the goal platform starts at most at
        ``size[0] - end_margin - goal_length`` - unless not even one stone fits, when it starts
        one gap (at most the largest ``gap_*`` bound) after the start platform. The flat layout
        puts its nominal goal exactly at the first bound.
        """
        goal_x1 = self.size[0] - self.end_margin
        no_stone = self.end_margin + self.start_length + max(self.gap_easy[1], self.gap_hard[1])
        return max(goal_x1 - self.goal_length, no_stone) - self.spawn_x


@dataclass
class CourseLayout:
    """One course: boxes in course order, in the sub-terrain's local frame (see module doc)."""

    center: np.ndarray
    """(N, 3) centre of each box's top face (x, y, z_top) [m]."""
    half_size: np.ndarray
    """(N, 2) half extents of each top face along x and y [m]."""
    role: np.ndarray
    """(N,) int: ROLE_START, ROLE_STONE, ROLE_PAIR or ROLE_GOAL."""
    step: np.ndarray
    """(N,) int: course step of each box; 0 start, 1..K stones (both stones of a pair share
    one step), K+1 goal."""
    origin: np.ndarray
    """(3,) spawn point: centre of the start platform's top face [m]."""
    size: tuple[float, float]
    """Sub-terrain extent (x, y) [m]."""
    bottom: float
    """z of the pit floor top; every box extends from its top down to here [m]."""
    goal_distance: float
    """Progress along +x from ``origin`` at which the goal platform begins [m]."""
    course_length: float
    """Progress along +x from ``origin`` to the far end of the goal platform [m]."""
    difficulty: float = 0.0
    """Difficulty the layout was drawn at (the stone difficulty for flat-first levels)."""
    kind: str = "stones"
    """"stones", "flat" or "hardware"."""
    name: str = ""
    """Geom name prefix in the compiled model (set by march.env.stone_terrain): box k is named
    f"{name}_{k:02d}" and the pit floor f"{name}_pit"."""

    @property
    def num_boxes(self) -> int:
        return int(self.center.shape[0])

    @property
    def top(self) -> np.ndarray:
        """(N,) top-face height of each box [m]."""
        return self.center[:, 2]

    @property
    def num_pairs(self) -> int:
        return int((self.role == ROLE_PAIR).sum()) // 2

    @property
    def num_steps(self) -> int:
        """Stepping-stone steps between the platforms (a pair counts once)."""
        return int(np.unique(self.step[(self.role == ROLE_STONE) | (self.role == ROLE_PAIR)]).size)

    def gaps(self) -> np.ndarray:
        """(K+1,) gaps along x between consecutive course steps [m]."""
        steps = np.unique(self.step)
        x0 = np.array(
            [
                (self.center[self.step == s, 0] - self.half_size[self.step == s, 0]).min()
                for s in steps
            ]
        )
        x1 = np.array(
            [
                (self.center[self.step == s, 0] + self.half_size[self.step == s, 0]).max()
                for s in steps
            ]
        )
        return x0[1:] - x1[:-1]


def _lerp(a: float, b: float, t: float) -> float:
    return float(a + (b - a) * t)


def _lerp_range(a: Range, b: Range, t: float) -> Range:
    return (_lerp(a[0], b[0], t), _lerp(a[1], b[1], t))


@dataclass
class DifficultyRanges:
    """The sampling ranges of one difficulty level [m]."""

    stone_size: Range
    gap: Range
    height: float
    lateral: Range


def difficulty_ranges(difficulty: float, cfg: CourseCfg) -> DifficultyRanges:
    """Interpolated sampling ranges at ``difficulty`` (clipped to [0, 1])."""
    t = float(np.clip(difficulty, 0.0, 1.0))
    return DifficultyRanges(
        stone_size=_lerp_range(cfg.stone_size_easy, cfg.stone_size_hard, t),
        gap=_lerp_range(cfg.gap_easy, cfg.gap_hard, t),
        height=_lerp(cfg.height_easy, cfg.height_hard, t),
        lateral=_lerp_range(cfg.lateral_easy, cfg.lateral_hard, t),
    )


class _Builder:
    """Accumulates boxes given by their x/y extents and top height."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float, float, float, int, int]] = []

    def add(self, x0: float, x1: float, yc: float, hy: float, z: float, role: int, step: int):
        self.rows.append((0.5 * (x0 + x1), yc, z, 0.5 * (x1 - x0), hy, role, step))

    def layout(
        self,
        cfg: CourseCfg,
        origin: np.ndarray,
        goal_x0: float,
        goal_x1: float,
        difficulty: float,
        kind: str,
    ) -> CourseLayout:
        a = np.array(self.rows, dtype=np.float64).reshape(-1, 7)
        return CourseLayout(
            center=a[:, 0:3].copy(),
            half_size=a[:, 3:5].copy(),
            role=a[:, 5].astype(np.int64),
            step=a[:, 6].astype(np.int64),
            origin=origin,
            size=tuple(cfg.size),
            bottom=-float(cfg.pit_depth),
            goal_distance=float(goal_x0 - origin[0]),
            course_length=float(goal_x1 - origin[0]),
            difficulty=float(difficulty),
            kind=kind,
        )


def _frame(cfg: CourseCfg) -> tuple[float, float, float, np.ndarray]:
    """(start platform end x, goal platform end x, y_mid, spawn origin) of a course."""
    x0 = cfg.end_margin
    x1 = x0 + cfg.start_length
    y_mid = 0.5 * cfg.size[1]
    origin = np.array([0.5 * (x0 + x1), y_mid, 0.0])
    return x1, cfg.size[0] - cfg.end_margin, y_mid, origin


def generate_course(difficulty: float, cfg: CourseCfg, rng: np.random.Generator) -> CourseLayout:
    """Draw one stepping-stone course at ``difficulty`` in [0, 1] (see :class:`CourseCfg`).

    Stones are laid from the start platform towards the goal: each step draws a gap and a
    stone length; steps are added while one more maximal gap and the minimum goal platform
    still fit, then the goal platform starts one drawn gap after the last stone and runs to
    ``size[0] - end_margin``. With probability ``pair_prob`` a step is a side-by-side pair.
    """
    r = difficulty_ranges(difficulty, cfg)
    start_x1, goal_x1, y_mid, origin = _frame(cfg)
    b = _Builder()
    hw = 0.5 * cfg.platform_width
    b.add(cfg.end_margin, start_x1, y_mid, hw, 0.0, ROLE_START, 0)

    x = start_x1
    side = 1.0 if rng.random() < 0.5 else -1.0
    step = 0
    while step < cfg.max_stones:
        gap = rng.uniform(*r.gap)
        sx = rng.uniform(*r.stone_size)
        if x + gap + sx + r.gap[1] + cfg.goal_length > goal_x1:
            break
        step += 1
        x0, x1 = x + gap, x + gap + sx
        if rng.random() < cfg.pair_prob:
            pg = rng.uniform(*cfg.pair_gap)
            for sgn in (1.0, -1.0):
                sy = rng.uniform(*r.stone_size)
                z = rng.uniform(-r.height, r.height)
                b.add(x0, x1, y_mid + sgn * 0.5 * (pg + sy), 0.5 * sy, z, ROLE_PAIR, step)
        else:
            sy = rng.uniform(*r.stone_size)
            z = rng.uniform(-r.height, r.height)
            b.add(x0, x1, y_mid + side * rng.uniform(*r.lateral), 0.5 * sy, z, ROLE_STONE, step)
        side = -side
        x = x1
    goal_x0 = x + rng.uniform(*r.gap)
    b.add(goal_x0, goal_x1, y_mid, hw, 0.0, ROLE_GOAL, step + 1)
    return b.layout(cfg, origin, goal_x0, goal_x1, difficulty, "stones")


def flat_course(cfg: CourseCfg) -> CourseLayout:
    """Flat ground (curriculum=flat_first): one platform covering the whole sub-terrain.

    The spawn point and ``goal_distance`` / ``course_length`` match a stone course's, so the
    distance and success metrics are comparable; index 0 is both the start and the goal.
    """
    _, goal_x1, y_mid, origin = _frame(cfg)
    b = _Builder()
    b.add(0.0, cfg.size[0], y_mid, 0.5 * cfg.size[1], 0.0, ROLE_START, 0)
    return b.layout(cfg, origin, goal_x1 - cfg.goal_length, goal_x1, 0.0, "flat")


def hardware_course(cfg: CourseCfg) -> CourseLayout:
    """The paper's hardware test: start platform, 4 stones alternating left/right, goal platform.

    All stones share the platforms' height (paper: "all the same height"); sizes, gaps and
    lateral offsets come from the ``hardware_*`` fields.
    """
    if len(cfg.hardware_gaps) != len(cfg.hardware_lateral) + 1:
        raise ValueError("hardware_gaps needs one more entry than hardware_lateral")
    start_x1, _, y_mid, origin = _frame(cfg)
    b = _Builder()
    hw = 0.5 * cfg.platform_width
    b.add(cfg.end_margin, start_x1, y_mid, hw, 0.0, ROLE_START, 0)
    x = start_x1
    sx, sy = cfg.hardware_stone_size
    for k, (gap, lat) in enumerate(
        zip(cfg.hardware_gaps[:-1], cfg.hardware_lateral, strict=True), start=1
    ):
        b.add(x + gap, x + gap + sx, y_mid + lat, 0.5 * sy, 0.0, ROLE_STONE, k)
        x += gap + sx
    goal_x0 = x + cfg.hardware_gaps[-1]
    goal_x1 = goal_x0 + cfg.goal_length
    if goal_x1 > cfg.size[0]:
        raise ValueError("hardware course longer than the sub-terrain")
    b.add(goal_x0, goal_x1, y_mid, hw, 0.0, ROLE_GOAL, len(cfg.hardware_lateral) + 1)
    return b.layout(cfg, origin, goal_x0, goal_x1, 0.0, "hardware")
