"""The stepping-stone world on mjlab: sub-terrains, the generator config and foothold ground truth.

How it plugs into mjlab (1.6.0)
- ``terrain_entity_cfg(kind, ...)`` returns a ``TerrainEntityCfg(terrain_type="generator",
  terrain_generator=terrain_generator_cfg(...))``; the env bridge sets ``env_cfg.scene.terrain`` to
  it. mjlab's ``TerrainGenerator`` lays a grid of ``num_rows`` x ``num_cols`` cells of
  ``CourseCfg.size`` (12 x 4 m): row r (along world x) is curriculum level r at difficulty
  r / (num_rows - 1), column c (along world y) one independently drawn course per level (in
  curriculum mode mjlab makes one column per sub-terrain entry, so we register ``num_cols``
  identical entries ``course_0..course_{C-1}``). Each course runs along world +x.
- Every cell is built by ``SubTerrainCfg.function(difficulty, spec, rng)`` with the generator's
  single ``np.random.default_rng(seed)``, called column by column, row by row (curriculum) or
  cell by cell (random mode). Its spawn origin (start platform centre) becomes
  ``TerrainEntity.terrain_origins[row, col]`` and each env's ``env_origins[e] =
  terrain_origins[terrain_levels[e], terrain_types[e]]``.

Foothold ground truth
- ``foothold_table(gen_cfg)`` re-runs mjlab's own ``TerrainGenerator`` on a scratch ``MjSpec``
  with the same config and seed (box geoms only, no compile: ~10 ms per cell) while recording
  every layout our sub-terrains emit, then files each layout under its (row, col) by matching
  its spawn point to ``terrain_origins``. Same seed + same call order = the same courses as the
  env's terrain; ``terrain_foothold_table(terrain)`` checks this against the live
  ``TerrainEntity.terrain_origins`` and ``max_model_mismatch`` against the compiled geoms.
  The generator seed must therefore be fixed (mjlab draws a random one when it is None).
- A command term builds the table once (``__init__``) and calls ``table.for_envs(
  terrain.terrain_levels[ids], terrain.terrain_types[ids], terrain.env_origins[ids])`` in its
  ``reset(env_ids)``: mjlab's ``_reset_idx`` runs the curriculum (which moves levels via
  ``TerrainEntity.update_env_origins``) before the command manager's reset, so the lookup
  always sees the env's new cell. The table never changes after build.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Literal

import mjlab  # noqa: F401  (before mujoco: mjlab sets MUJOCO_GL=egl, which mujoco reads once)
import mujoco
import numpy as np
import torch
from mjlab.terrains import TerrainEntity, TerrainEntityCfg
from mjlab.terrains.terrain_generator import (
    SubTerrainCfg,
    TerrainGenerator,
    TerrainGeneratorCfg,
    TerrainGeometry,
    TerrainOutput,
)

from march.world.courses import (
    ROLE_GOAL,
    ROLE_START,
    CourseCfg,
    CourseLayout,
    flat_course,
    generate_course,
    hardware_course,
)
from march.world.footholds import FootholdTable

TerrainKind = Literal["stones", "flat_first", "flat", "hardware"]
KINDS: tuple[str, ...] = ("stones", "flat_first", "flat", "hardware")

_PLATFORM_RGBA = (0.55, 0.55, 0.6, 1.0)
_PIT_RGBA = (0.08, 0.08, 0.1, 1.0)
_LOW_RGBA = np.array([0.2, 0.4, 0.85, 1.0])
_HIGH_RGBA = np.array([0.95, 0.75, 0.25, 1.0])


# --------------------------------------------------------------------------------------------
# Recording layouts while mjlab's generator runs.


@dataclass
class _Record:
    layout: CourseLayout
    geom: mujoco.MjsGeom
    local_pos: np.ndarray


@dataclass
class LayoutRecorder:
    """Collects the layouts our sub-terrains build while active (see :func:`record_layouts`)."""

    records: list[_Record] = field(default_factory=list)

    def grid(self, terrain_origins: np.ndarray | torch.Tensor) -> list[list[CourseLayout]]:
        """Layouts as a [row][col] grid, matched to ``terrain_origins`` (R, C, 3).

        mjlab moves each sub-terrain's geoms by its cell corner after ``function`` returns; the
        recorded first geom's displacement gives the corner, corner + layout origin the spawn
        point, and the spawn point its cell.
        """
        origins = np.asarray(
            terrain_origins.cpu() if isinstance(terrain_origins, torch.Tensor) else terrain_origins,
            dtype=np.float64,
        )
        rows, cols = origins.shape[:2]
        flat = origins.reshape(-1, 3)
        grid: list[list[CourseLayout | None]] = [[None] * cols for _ in range(rows)]
        for rec in self.records:
            corner = np.asarray(rec.geom.pos, dtype=np.float64) - rec.local_pos
            spawn = corner + rec.layout.origin
            i = int(np.argmin(np.abs(flat - spawn).max(axis=1)))
            if np.abs(flat[i] - spawn).max() > 1e-6:
                raise RuntimeError(f"layout spawn {spawn} matches no terrain origin")
            r, c = divmod(i, cols)
            if grid[r][c] is not None:
                raise RuntimeError(f"two layouts recorded for cell ({r}, {c})")
            grid[r][c] = rec.layout
        missing = [(r, c) for r in range(rows) for c in range(cols) if grid[r][c] is None]
        if missing:
            raise RuntimeError(
                f"no march course recorded for cells {missing[:5]} "
                "(a generator mixing in non-march sub-terrains has no footholds)"
            )
        return [[lay for lay in row if lay is not None] for row in grid]


_ACTIVE: list[LayoutRecorder] = []


@contextmanager
def record_layouts() -> Iterator[LayoutRecorder]:
    """Record every layout built by march sub-terrains inside the ``with`` block."""
    rec = LayoutRecorder()
    _ACTIVE.append(rec)
    try:
        yield rec
    finally:
        _ACTIVE.remove(rec)


# --------------------------------------------------------------------------------------------
# Sub-terrains.


def _height_rgba(top: float, span: float) -> tuple[float, float, float, float]:
    t = 0.5 if span <= 0 else float(np.clip(0.5 + 0.5 * top / span, 0.0, 1.0))
    return tuple(float(v) for v in (1 - t) * _LOW_RGBA + t * _HIGH_RGBA)  # type: ignore[return-value]


def build_layout(spec: mujoco.MjSpec, layout: CourseLayout, add_pit: bool = True) -> TerrainOutput:
    """Add ``layout``'s boxes (and a pit floor) to the spec's "terrain" body.

    Geom names: box k is f"{prefix}_{k:02d}", the pit floor f"{prefix}_pit", with prefix
    f"course{n:05d}" where n is the number of geoms in the body before this call (unique within
    a spec, and identical when the same generator is re-run); stored in ``layout.name``.
    """
    body = spec.body("terrain")
    prefix = f"course{len(body.geoms):05d}"
    layout.name = prefix
    geometries: list[TerrainGeometry] = []
    span = float(np.abs(layout.top).max()) if layout.num_boxes else 0.0
    first_pos = None
    for k in range(layout.num_boxes):
        cx, cy, top = layout.center[k]
        hx, hy = layout.half_size[k]
        hz = 0.5 * (top - layout.bottom)
        pos = np.array([cx, cy, top - hz])
        geom = body.add_geom(
            name=f"{prefix}_{k:02d}", type=mujoco.mjtGeom.mjGEOM_BOX, size=(hx, hy, hz), pos=pos
        )
        role = layout.role[k]
        color = _PLATFORM_RGBA if role in (ROLE_START, ROLE_GOAL) else _height_rgba(top, span)
        geometries.append(TerrainGeometry(geom=geom, color=color))
        if first_pos is None:
            first_pos = (geom, pos)
    if add_pit:
        sx, sy = layout.size
        pos = np.array([0.5 * sx, 0.5 * sy, layout.bottom - 0.05])
        geom = body.add_geom(
            name=f"{prefix}_pit",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=(0.5 * sx, 0.5 * sy, 0.05),
            pos=pos,
        )
        geometries.append(TerrainGeometry(geom=geom, color=_PIT_RGBA))
    assert first_pos is not None
    for rec in _ACTIVE:
        rec.records.append(_Record(layout=layout, geom=first_pos[0], local_pos=first_pos[1]))
    return TerrainOutput(origin=layout.origin.copy(), geometries=geometries)


def _course_cfg(course: CourseCfg, size: tuple[float, float]) -> CourseCfg:
    """The course config with mjlab's cell size (the generator overwrites SubTerrainCfg.size)."""
    return dataclasses.replace(course, size=(float(size[0]), float(size[1])))


@dataclass(kw_only=True)
class StoneCourseTerrainCfg(SubTerrainCfg):
    """Start platform, stepping stones (with side-by-side pairs), goal platform; along +x."""

    course: CourseCfg = field(default_factory=CourseCfg)
    """Course geometry; its ``size`` is replaced by the generator's cell size."""
    flat_below: float = 0.0
    """Cells generated at difficulty < flat_below are flat ground (curriculum=flat_first); the
    others get stone difficulty (d - flat_below) / (1 - flat_below)."""

    def layout(self, difficulty: float, rng: np.random.Generator) -> CourseLayout:
        course = _course_cfg(self.course, self.size)
        if difficulty < self.flat_below:
            return flat_course(course)
        d = (difficulty - self.flat_below) / max(1.0 - self.flat_below, 1e-9)
        return generate_course(float(np.clip(d, 0.0, 1.0)), course, rng)

    def function(
        self, difficulty: float, spec: mujoco.MjSpec, rng: np.random.Generator
    ) -> TerrainOutput:
        lay = self.layout(difficulty, rng)
        return build_layout(spec, lay, add_pit=lay.kind != "flat")


@dataclass(kw_only=True)
class FlatCourseTerrainCfg(SubTerrainCfg):
    """Flat ground: one platform covering the cell, spawn point as on a stone course."""

    course: CourseCfg = field(default_factory=CourseCfg)
    """Course geometry (spawn point, nominal goal); ``size`` is the generator's cell size."""

    def function(
        self, difficulty: float, spec: mujoco.MjSpec, rng: np.random.Generator
    ) -> TerrainOutput:
        del difficulty, rng
        return build_layout(spec, flat_course(_course_cfg(self.course, self.size)), add_pit=False)


@dataclass(kw_only=True)
class HardwareCourseTerrainCfg(SubTerrainCfg):
    """The paper's hardware test course (ignores difficulty)."""

    course: CourseCfg = field(default_factory=CourseCfg)
    """Course geometry; the ``hardware_*`` fields place the 4 stones."""

    def function(
        self, difficulty: float, spec: mujoco.MjSpec, rng: np.random.Generator
    ) -> TerrainOutput:
        del difficulty, rng
        return build_layout(spec, hardware_course(_course_cfg(self.course, self.size)))


# --------------------------------------------------------------------------------------------
# Generator / entity configs.


def terrain_generator_cfg(
    kind: str = "stones",
    course: CourseCfg | None = None,
    *,
    num_rows: int = 10,
    num_cols: int = 8,
    seed: int = 0,
    curriculum: bool = True,
    flat_levels: int = 2,
    border_width: float = 0.0,
) -> TerrainGeneratorCfg:
    """mjlab generator config for ``kind``:

    - "stones": ``num_rows`` levels (rows) at difficulty row / (num_rows - 1), ``num_cols``
      independent courses per level.
    - "flat_first": as "stones", but the lowest ``flat_levels`` levels are flat ground and the
      stone levels above them span difficulty 0..1 (start envs at level 0 with
      ``max_init_terrain_level=0``; mjlab's level curriculum then moves them onto stones).
    - "flat": flat ground at every level.
    - "hardware": a single cell with the hardware course (num_rows / num_cols ignored).

    ``curriculum=False`` uses mjlab's random mode instead (each cell a uniform difficulty);
    evaluation over all levels can also keep curriculum mode with ``max_init_terrain_level``
    = None (levels drawn uniformly). ``seed`` must stay fixed: the foothold table regenerates
    the terrain from it.
    """
    if kind not in KINDS:
        raise ValueError(f"terrain kind {kind!r}: use one of {KINDS}")
    course = course if course is not None else CourseCfg()
    subs: dict[str, SubTerrainCfg]
    if kind == "hardware":
        num_rows, num_cols = 1, 1
        subs = {"hardware": HardwareCourseTerrainCfg(course=course)}
    elif kind == "flat":
        subs = {f"flat_{c}": FlatCourseTerrainCfg(course=course) for c in range(num_cols)}
    else:
        flat_below = 0.0
        if kind == "flat_first":
            if not 0 < flat_levels < num_rows:
                raise ValueError(f"flat_levels={flat_levels} must be in [1, num_rows)")
            flat_below = flat_levels / (num_rows - 1) - 1e-6
        subs = {
            f"course_{c}": StoneCourseTerrainCfg(course=course, flat_below=flat_below)
            for c in range(num_cols)
        }
    return TerrainGeneratorCfg(
        seed=seed,
        curriculum=curriculum,
        size=tuple(course.size),
        border_width=border_width,
        num_rows=num_rows,
        num_cols=num_cols,
        sub_terrains=subs,
        difficulty_range=(0.0, 1.0),
        color_scheme="height",
        add_lights=True,
    )


def terrain_entity_cfg(
    kind: str = "stones",
    course: CourseCfg | None = None,
    *,
    max_init_terrain_level: int | None = 0,
    **generator_kwargs,
) -> TerrainEntityCfg:
    """``env_cfg.scene.terrain`` for ``kind``: mjlab's generator terrain (see
    :func:`terrain_generator_cfg` for the keyword arguments)."""
    return TerrainEntityCfg(
        terrain_type="generator",
        terrain_generator=terrain_generator_cfg(kind, course, **generator_kwargs),
        max_init_terrain_level=max_init_terrain_level,
    )


# --------------------------------------------------------------------------------------------
# Foothold ground truth.


def foothold_table(
    gen_cfg: TerrainGeneratorCfg, device: torch.device | str = "cpu"
) -> FootholdTable:
    """The FootholdTable of the terrain mjlab builds from ``gen_cfg`` (see module doc)."""
    if gen_cfg.seed is None:
        raise ValueError(
            "foothold_table needs TerrainGeneratorCfg.seed set (mjlab draws a "
            "random seed otherwise and the courses cannot be reproduced)"
        )
    cfg = copy.deepcopy(gen_cfg)
    with record_layouts() as rec:
        gen = TerrainGenerator(cfg, device="cpu")
        gen.compile(mujoco.MjSpec())
    grid = rec.grid(gen.terrain_origins)
    return FootholdTable.from_layouts(grid, gen.terrain_origins, device)


def terrain_foothold_table(
    terrain: TerrainEntity, device: torch.device | str | None = None
) -> FootholdTable:
    """The FootholdTable of a built ``env.scene.terrain``, checked against its origins."""
    gen_cfg = terrain.cfg.terrain_generator
    if terrain.cfg.terrain_type != "generator" or gen_cfg is None:
        raise ValueError("the terrain is not a generator terrain: no stepping-stone courses")
    assert terrain.terrain_origins is not None
    dev = device if device is not None else terrain.terrain_origins.device
    table = foothold_table(gen_cfg, dev)
    live = terrain.terrain_origins.to(table.origins.device, torch.float32)
    if live.shape != table.origins.shape or not torch.allclose(live, table.origins, atol=1e-5):
        raise RuntimeError(
            "regenerated terrain origins differ from the env's terrain: "
            "was the generator config changed after the env was built?"
        )
    return table


def max_model_mismatch(table: FootholdTable, model: mujoco.MjModel) -> float:
    """Largest |difference| [m] between the table's boxes (world top-face centre, half sizes)
    and the compiled model's geoms of the same name; inf if a geom is missing or the model has
    course geoms the table lacks. The terrain body sits at the world origin (mjlab attaches it
    with an identity frame), so geom_pos is world."""
    world = table.world_center().cpu().numpy()
    half = table.half_size.cpu().numpy()
    valid = table.valid.cpu().numpy()
    worst = 0.0
    expected = 0
    for r, row in enumerate(table.layouts):
        for c, lay in enumerate(row):
            for k in np.flatnonzero(valid[r, c]):
                expected += 1
                try:
                    g = model.geom(f"{lay.name}_{k:02d}")
                except KeyError:
                    return float("inf")
                top = np.array(g.pos) + np.array([0.0, 0.0, g.size[2]])
                worst = max(
                    worst,
                    float(np.abs(top - world[r, c, k]).max()),
                    float(np.abs(np.array(g.size[:2]) - half[r, c, k]).max()),
                )
    names = [model.geom(i).name for i in range(model.ngeom)]
    found = sum(1 for n in names if n.startswith("course") and not n.endswith("_pit"))
    return worst if found == expected else float("inf")


def terrain_boxes(table: FootholdTable, neighbours: int = 1) -> tuple[torch.Tensor, ...]:
    """Every terrain box a ray from cell (r, c) can hit, for an analytic height scan.

    Returns ``(top_center, half_size, valid)``, shapes (R, C, K, 3), (R, C, K, 2), (R, C, K):
    world top-face centres and half extents of the boxes of cell (r, c) and of the cells
    ``neighbours`` rows before and after it in the same column (rows are laid end to end along
    x, so a robot at either end of its course sees the next / previous level's platform), each
    cell's stones and platforms (the foothold table) plus its pit floor (a box over the whole
    cell whose top is ``layout.bottom``; flat cells have none). Padding and cells beyond the
    grid are ``valid = False``. Cells beside (other columns) are 4 m apart and out of reach of
    a scan around a robot on its course's platforms or stones.
    """
    rows, cols, s = table.shape
    pit_center = np.zeros((rows, cols, 1, 3))
    pit_half = np.zeros((rows, cols, 1, 2))
    pit_valid = np.zeros((rows, cols, 1), dtype=bool)
    for r, row in enumerate(table.layouts):
        for c, lay in enumerate(row):
            if lay.kind == "flat":
                continue
            sx, sy = lay.size
            pit_center[r, c, 0] = (0.5 * sx, 0.5 * sy, lay.bottom) - lay.origin
            pit_half[r, c, 0] = (0.5 * sx, 0.5 * sy)
            pit_valid[r, c, 0] = True
    dev = table.center.device
    center = torch.cat([table.center, torch.as_tensor(pit_center, dtype=torch.float32).to(dev)], 2)
    center = center + table.origins[:, :, None, :]
    half = torch.cat([table.half_size, torch.as_tensor(pit_half, dtype=torch.float32).to(dev)], 2)
    valid = torch.cat([table.valid, torch.as_tensor(pit_valid).to(dev)], 2)
    parts_c, parts_h, parts_v = [], [], []
    for dr in range(-neighbours, neighbours + 1):
        src = torch.arange(rows, device=dev) + dr
        inside = (src >= 0) & (src < rows)
        src = src.clamp(0, rows - 1)
        parts_c.append(center[src])
        parts_h.append(half[src])
        parts_v.append(valid[src] & inside[:, None, None])
    return torch.cat(parts_c, 2), torch.cat(parts_h, 2), torch.cat(parts_v, 2)


def max_boxes_in_reach(
    top_center: torch.Tensor, half: torch.Tensor, valid: torch.Tensor, reach: float
) -> int:
    """The most boxes of one cell's :func:`terrain_boxes` whose x-extent comes within ``reach``
    [m] of one point, over all points and cells: a box [lo, hi] is within reach of x iff x lies
    in [lo - reach, hi + reach], and the largest overlap of those widened intervals is attained
    at one of their left ends. Computed once per env on the host."""
    lo = (top_center[..., 0] - half[..., 0] - reach).reshape(-1, valid.shape[-1])
    hi = (top_center[..., 0] + half[..., 0] + reach).reshape(-1, valid.shape[-1])
    v = valid.reshape(-1, valid.shape[-1])
    lo = lo.masked_fill(~v, float("inf")).cpu()
    hi = hi.masked_fill(~v, -float("inf")).cpu()
    at = lo[:, :, None]  # candidate points (cells, K, 1)
    count = ((lo[:, None, :] <= at) & (at <= hi[:, None, :])).sum(-1)  # (cells, K)
    return max(1, int(count.max()))
