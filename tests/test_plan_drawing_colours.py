"""The plan drawing's colours against the course's (issue 48: blue left-foot balls and the yellow
target post were hard to tell from the course's blue and yellow boxes).

Every marker colour of :mod:`march.env.plan_drawing` must be at least ``MIN_DELTA_E`` CIELAB
units (CIE 1976 delta E) from every colour a course box can have and from every other marker.
The box colours: :func:`march.env.stone_terrain._height_rgba` sampled over its whole range
(it clips to the blue-grey-yellow segment), the start/goal platforms, the pit floor and
mjlab's border; a compiled terrain of every kind is read back to check that no box has a colour
outside that set. CIELAB is computed here from the sRGB definition (IEC 61966-2-1 decoding,
sRGB/D65 matrix, CIE 1976 L*a*b*), checked against published values.

Two readings of an RGBA value are checked, since the renderers differ: as sRGB (what the value
means written straight into an 8-bit frame) and as linear light, encoded to sRGB for display
(what viser / three.js does: in the docs' capture the target post's (0.95, 0.15, 0.05) showed
as about (0.94, 0.52, 0.29), a box's grey 0.575 as 0.82). Boxes and markers go through the same
reading in one renderer, so each pair is compared within a reading.

The threshold: in the viewer a box is seen lit and in shade; a box colour at half the light
(linear RGB x 0.5) is up to ~24 units from itself at full light (measured below over all box
colours, both readings). A marker at 50 (twice that) cannot pass for a shaded or lit face of
any box, and two markers cannot pass for one another in shade either. The considered-stone
slab is translucent: the tint it gives every box must exceed what half the light does (25).
The old colours fail (last test).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from march.env import plan_drawing
from march.env.stone_terrain import _HIGH_RGBA, _LOW_RGBA, _PIT_RGBA, _PLATFORM_RGBA, _height_rgba

MIN_DELTA_E = 50.0
"""Smallest CIELAB (CIE76) distance allowed: marker-box and marker-marker."""
MJLAB_BORDER_RGBA = (0.2, 0.2, 0.2, 1.0)
"""mjlab's terrain border (``terrain_generator._DARK_GRAY``; read back from a compiled border
below)."""

_SRGB_TO_XYZ = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
_D65_WHITE = np.array([0.95047, 1.0, 1.08883])


def _linear(srgb: np.ndarray) -> np.ndarray:
    c = np.asarray(srgb, dtype=np.float64)[..., :3]
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _encode(linear: np.ndarray) -> np.ndarray:
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def srgb_to_lab(srgb) -> np.ndarray:  # noqa: ANN001
    """(..., 3 or 4) sRGB in [0, 1] -> (..., 3) CIELAB (D65); alpha is ignored."""
    xyz = _linear(srgb) @ _SRGB_TO_XYZ.T / _D65_WHITE
    eps = (6 / 29) ** 3
    f = np.where(xyz > eps, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack(
        [116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1
    )


def delta_e(a, b) -> np.ndarray:  # noqa: ANN001
    """CIE76 colour difference between sRGB colours (broadcasting)."""
    return np.linalg.norm(srgb_to_lab(a) - srgb_to_lab(b), axis=-1)


READINGS = {
    "as sRGB": lambda rgba: np.asarray(rgba, dtype=np.float64)[..., :3],
    "as linear light (viser)": lambda rgba: _encode(np.asarray(rgba, dtype=np.float64)[..., :3]),
}
"""An RGBA value -> the sRGB colour shown, in each of the two readings."""


def box_colours() -> dict[str, np.ndarray]:
    """Every colour a course box can have, by name (the height map sampled 1201 times over and
    beyond its range: tops from -1.5 to 1.5 spans, clipped at both ends, and a zero span)."""
    tops = np.linspace(-1.5, 1.5, 1201)
    height = np.array([_height_rgba(float(t), 1.0) for t in tops] + [_height_rgba(0.3, 0.0)])
    out = {f"height {t:+.4f}": c for t, c in zip(tops, height[:-1], strict=True)}
    out["height (flat course)"] = height[-1]
    out["platform"] = np.array(_PLATFORM_RGBA)
    out["pit"] = np.array(_PIT_RGBA)
    out["mjlab border"] = np.array(MJLAB_BORDER_RGBA)
    return out


def _closest(colour, table: dict[str, np.ndarray], shown=READINGS["as sRGB"]):  # noqa: ANN001
    """(distance, name) of the colour in ``table`` nearest ``colour``, both read by ``shown``."""
    names = list(table)
    d = delta_e(shown(np.asarray(colour)[None]), shown(np.stack([table[n] for n in names])))
    return float(d.min()), names[int(d.argmin())]


def test_lab_matches_published_values():
    """sRGB primaries, white, black and mid-grey against their published CIELAB (D65)
    coordinates; red vs blue by hand: sqrt((53.24-32.30)^2 + (80.09-79.19)^2 +
    (67.20+107.86)^2) = sqrt(438.5 + 0.81 + 30646) = 176.31."""
    cases = {
        (1.0, 0.0, 0.0): (53.24, 80.09, 67.20),
        (0.0, 1.0, 0.0): (87.73, -86.18, 83.18),
        (0.0, 0.0, 1.0): (32.30, 79.19, -107.86),
        (1.0, 1.0, 1.0): (100.0, 0.0, 0.0),
        (0.0, 0.0, 0.0): (0.0, 0.0, 0.0),
        (0.5, 0.5, 0.5): (53.39, 0.0, 0.0),
    }
    for rgb, lab in cases.items():
        assert srgb_to_lab(np.array(rgb)) == pytest.approx(lab, abs=0.02), rgb
    assert float(delta_e((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))) == pytest.approx(176.31, abs=0.02)


def test_the_box_colours_cover_the_height_map_and_every_compiled_terrain():
    """The sampled height map reaches both ends (low blue, high yellow) and its midpoint; every
    box geom of a compiled terrain of every kind (with mjlab's border) is one of the sampled
    colours (within 0.5 units: the samples are ~0.1 apart)."""
    import mujoco
    from mjlab.terrains import TerrainGenerator

    from march.env.stone_terrain import KINDS, terrain_generator_cfg

    boxes = box_colours()
    table = np.stack(list(boxes.values()))
    assert table[0] == pytest.approx(_LOW_RGBA) and table[1200] == pytest.approx(_HIGH_RGBA)
    assert table[600] == pytest.approx(0.5 * (_LOW_RGBA + _HIGH_RGBA))
    steps = delta_e(table[1:1200], table[:1199])
    assert steps.max() < 0.5
    seen = 0
    for kind in KINDS:
        cfg = terrain_generator_cfg(kind, num_rows=3, num_cols=2, seed=3, border_width=1.0)
        spec = mujoco.MjSpec()
        TerrainGenerator(cfg).compile(spec)
        model = spec.compile()
        for g in range(model.ngeom):
            if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_BOX:
                continue
            d, name = _closest(model.geom_rgba[g], boxes)
            assert d < 0.5, (kind, model.geom(g).name, model.geom_rgba[g], name, d)
            seen += 1
    assert seen > 100


def _half_light(rgba: np.ndarray) -> np.ndarray:
    """The RGBA value that shows as ``rgba`` at half the light (linear RGB x 0.5), per reading
    (as sRGB: decode, halve, encode; as linear light: halve)."""
    return {
        "as sRGB": _encode(0.5 * _linear(rgba)),
        "as linear light (viser)": 0.5 * np.asarray(rgba, dtype=np.float64)[..., :3],
    }


def test_the_threshold_is_twice_what_shade_does_to_a_box():
    """The largest distance between a box colour lit and at half the light is ~24 units in
    either reading; MIN_DELTA_E is at least twice it."""
    table = np.stack(list(box_colours().values()))[:, :3]
    for reading, shown in READINGS.items():
        shade = max(float(delta_e(shown(c), shown(_half_light(c)[reading]))) for c in table)
        assert 20.0 < shade <= MIN_DELTA_E / 2, (reading, shade)


@pytest.mark.parametrize("reading", list(READINGS))
def test_every_marker_is_far_from_every_box_colour(reading):
    boxes = box_colours()
    for marker, rgba in plan_drawing.MARKER_RGBAS.items():
        d, box = _closest(rgba, boxes, READINGS[reading])
        assert d >= MIN_DELTA_E, f"{reading}: {marker} {rgba} is {d:.1f} from the {box} box"


@pytest.mark.parametrize("reading", list(READINGS))
def test_the_markers_are_far_from_each_other(reading):
    shown = READINGS[reading]
    for (a, ca), (b, cb) in itertools.combinations(plan_drawing.MARKER_RGBAS.items(), 2):
        d = float(delta_e(shown(np.array(ca)), shown(np.array(cb))))
        assert d >= MIN_DELTA_E, f"{reading}: {a} {ca} and {b} {cb} are {d:.1f} apart"


def test_a_considered_stone_slab_tints_every_box_more_than_shade_does():
    """The slab (``STONE_RGBA`` at its alpha) over each box colour, blended in the reading's
    light (sRGB values for the first, linear for viser), is at least MIN_DELTA_E / 2 from the
    bare box."""
    slab = np.array(plan_drawing.STONE_RGBA)
    alpha = slab[3]
    for reading, shown in READINGS.items():
        for name, box in box_colours().items():
            tinted = alpha * slab[:3] + (1 - alpha) * box[:3]
            d = float(delta_e(shown(tinted), shown(box)))
            assert d >= MIN_DELTA_E / 2, f"{reading}: the slab tints the {name} box by {d:.1f}"


def test_the_drawing_uses_only_the_listed_colours():
    """Every colour drawn (recorded through a fake visualizer on a made-up picture) is one of
    MARKER_RGBAS, and each listed colour is drawn."""
    pic = {
        "stone_center": np.zeros((2, 3)),
        "stone_half": np.full((2, 3), 0.1),
        "com_path": np.linspace([0, 0, 0.7], [0.3, 0, 0.7], 4),
        "com_now": np.array([0.1, 0.0, 0.7]),
        "target": np.array([0.3, 0.1, 0.0]),
        "swing_foot": np.array([0.0, 0.1, 0.0]),
        "footholds": np.array([[0.3, 0.1, 0.0], [0.6, -0.1, 0.0]]),
        "lands_left": np.array([True, False]),
    }
    used: list[tuple] = []

    class Vis:
        def add_box(self, *a):  # noqa: ANN002
            used.append(tuple(a[3]))

        def add_sphere(self, *a, label=None):  # noqa: ANN001, ANN002
            used.append(tuple(a[2]))

        def add_cylinder(self, *a):  # noqa: ANN002
            used.append(tuple(a[3]))

        def add_arrow(self, *a):  # noqa: ANN002
            used.append(tuple(a[2]))

    plan_drawing.draw_picture(pic, Vis())
    assert set(used) == set(plan_drawing.MARKER_RGBAS.values())


def test_the_old_colours_fail():
    """The colours issue 48 complained of (read as sRGB): blue left-foot balls 7 units from the
    low boxes' blue, the yellow target post 23 from the high boxes' yellow, the orange CoM 33."""
    boxes = box_colours()
    old = {"left": (0.12, 0.47, 0.90), "target": (1.0, 0.85, 0.0), "com": (1.0, 0.55, 0.0)}
    got = {k: round(_closest(c, boxes)[0], 1) for k, c in old.items()}
    assert got == {"left": 7.4, "target": 23.0, "com": 33.2}
    assert all(d < MIN_DELTA_E for d in got.values())
