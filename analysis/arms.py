"""The arms and variants the figures draw, how they look, and which pairs are compared.

Reward arms (``reward.name``) and student variants (``student.variant``) are data: each option of
``conf/reward/`` and ``conf/student/`` states its ``label``, ``color`` and ``order``, every run's
``config.yaml`` records them, and this module reads both (a run's own values win; the repository's
conf tree fills in runs written before the fields existed). An arm nobody gave a colour, or one
whose colour another arm already has, gets the first palette colour no other arm uses, so two
series never share a colour without a warning.

Comparisons are chosen, not written in (:class:`Comparisons`): arm pairs ``A:B`` (relative
difference (A - B) / B, student = the reference variant), and the ablation (each variant of one
teacher arm against the reference variant). The command line wins, then what the runs' config
names (``figures.compare`` etc., set by a sweep file), then the paper's pairs.

Reads files only (omegaconf); never imports march.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

from analysis.rundirs import Run

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
PAPER_PAIRS = (("clf", "modelfree"),)
PAPER_ABLATION_TEACHER = "clf"
PAPER_REFERENCE_VARIANT = "full"
PAPER_VARIANTS = ("full", "no_transformer", "no_mdn")  # the paper's ablation, when none is named
PALETTE = (
    "tab:blue",
    "tab:red",
    "tab:green",
    "tab:orange",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
    "tab:gray",
    "black",
    "gold",
    "navy",
    "teal",
)
GROUP_KEY = {"reward": "name", "student": "variant"}
ATTR = {"reward": "reward", "student": "variant"}


@dataclass(frozen=True)
class Series:
    name: str
    label: str
    color: str
    order: int


@dataclass
class Comparisons:
    """Which pairs the figures and tables compare, and which series a sweep asked for."""

    pairs: list[tuple[str, str]] = field(default_factory=lambda: list(PAPER_PAIRS))
    ablation_teacher: str = PAPER_ABLATION_TEACHER
    reference_variant: str = PAPER_REFERENCE_VARIANT
    expected_arms: list[str] = field(default_factory=list)
    expected_variants: list[str] = field(default_factory=list)
    source: str = "the paper's pairs"
    arm_order: list[str] = field(default_factory=list)  # legend / table order of the arms
    variant_order: list[str] = field(default_factory=list)
    arms: dict[str, Series] = field(default_factory=dict)  # name -> label, colour, order
    variants: dict[str, Series] = field(default_factory=dict)

    @property
    def title(self) -> str:
        return ", ".join(f"{a} vs {b}" for a, b in self.pairs)


def _yaml(path: Path) -> dict:
    try:
        node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except Exception:  # noqa: BLE001 - a broken option file must not stop the figures
        return {}
    return node if isinstance(node, dict) else {}


def conf_options(group: str, conf_dir: Path = CONF_DIR) -> dict[str, dict]:
    """name -> the option's YAML (``conf/<group>/*.yaml``) of the repository's conf tree."""
    out = {}
    for path in sorted((conf_dir / group).glob("*.yaml")):
        data = _yaml(path)
        out[str(data.get(GROUP_KEY[group]) or path.stem)] = data
    return out


def _is_color(value: str) -> bool:
    try:
        from matplotlib.colors import is_color_like
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        return bool(value)
    return bool(value) and is_color_like(value)


def series_table(
    runs: list[Run], group: str, notes: list[str], conf_dir: Path = CONF_DIR
) -> dict[str, Series]:
    """name -> :class:`Series` for every option of ``group`` found in the runs or the conf tree,
    each with a colour no other one has (a clash or an invalid colour is noted and replaced)."""
    meta: dict[str, dict] = {k: dict(v) for k, v in conf_options(group, conf_dir).items()}
    for run in runs:
        name = getattr(run, ATTR[group])
        own = run.meta.get(group, {})
        meta.setdefault(name, {}).update({k: v for k, v in own.items() if v not in (None, "")})

    def order(name: str) -> int:
        value = meta[name].get("order")
        return 100 if value in (None, "") else int(value)

    ordered = sorted(meta, key=lambda n: (order(n), n))
    used: set[str] = set()
    table: dict[str, Series] = {}
    found = {getattr(r, ATTR[group]) for r in runs}
    for name in ordered:
        color = str(meta[name].get("color") or "")
        if color and not _is_color(color):
            if name in found:
                notes.append(f"{group} {name}: colour {color!r} is not a matplotlib colour")
            color = ""
        if color in used:
            if name in found:
                notes.append(f"{group} {name}: colour {color} is taken; drawn in another")
            color = ""
        if not color:
            color = next((c for c in PALETTE if c not in used), "black")
        used.add(color)
        table[name] = Series(
            name=name,
            label=str(meta[name].get("label") or name),
            color=color,
            order=order(name),
        )
    return table


def _arm_reward(arm: str, conf_dir: Path) -> str:
    """The reward name an ``+experiment=<arm>`` choice selects (its ``override /reward: X``)."""
    data = _yaml(conf_dir / "experiment" / f"{arm}.yaml")
    for item in data.get("defaults", []) or []:
        if isinstance(item, dict):
            for key, value in item.items():
                if str(key).split()[-1].strip("/") == "reward":
                    return str(value)
    return arm


def _reward_name(option: str, conf_dir: Path) -> str:
    """The ``name:`` of ``conf/reward/<option>.yaml`` (the option itself if it has none)."""
    return str(_yaml(conf_dir / "reward" / f"{option}.yaml").get("name") or option)


def _split(value) -> list[str]:
    if isinstance(value, (list, tuple)):
        return [str(v) for v in value]
    text = str(value)
    for prefix in ("choice(", "range("):
        if text.startswith(prefix) and text.endswith(")"):
            text = text[len(prefix) : -1]
    return [v.strip() for v in text.split(",") if v.strip()]


def sweep_requests(dirs: list[Path], conf_dir: Path = CONF_DIR) -> tuple[list[str], list[str]]:
    """The reward arms and student variants the sweeps under ``dirs`` asked for (their
    ``multirun.yaml``: ``hydra.sweeper.params`` and ``hydra.overrides.task``)."""
    arms: list[str] = []
    variants: list[str] = []
    for root in dirs:
        for path in sorted(Path(root).rglob("multirun.yaml")):
            data = _yaml(path).get("hydra", {}) or {}
            params = dict((data.get("sweeper", {}) or {}).get("params", {}) or {})
            for item in (data.get("overrides", {}) or {}).get("task", []) or []:
                if "=" in str(item):
                    key, value = str(item).split("=", 1)
                    params.setdefault(key, value)
            for key, value in params.items():
                group = str(key).lstrip("+~")
                if group == "reward":
                    arms += [_reward_name(v, conf_dir) for v in _split(value)]
                elif group in ("experiment", "arm"):  # arm: the old name, in older sweeps
                    arms += [_arm_reward(v, conf_dir) for v in _split(value)]
                elif group == "student":
                    variants += _split(value)
    return list(dict.fromkeys(arms)), list(dict.fromkeys(variants))


def parse_pair(text: str) -> tuple[str, str]:
    """``A:B`` -> (A, B); anything else is a ValueError with the form expected."""
    parts = text.split(":")
    if len(parts) != 2 or not all(p.strip() for p in parts) or parts[0] == parts[1]:
        raise ValueError(f"--compare {text!r}: expected ARM:REFERENCE with two different arms")
    return parts[0].strip(), parts[1].strip()


def choose(
    runs: list[Run],
    dirs: list[Path],
    compare: list[str] | None = None,
    reference_variant: str | None = None,
    ablation_teacher: str | None = None,
    notes: list[str] | None = None,
    conf_dir: Path = CONF_DIR,
) -> Comparisons:
    """The comparisons: command line first, then the runs' ``figures.*`` config, then the
    paper's pairs. Raises ValueError on a malformed pair."""
    notes = [] if notes is None else notes
    out = Comparisons()
    named = [r.figures for r in runs if r.figures]
    if compare:
        out.pairs = [parse_pair(c) for c in compare]
        out.source = "--compare"
    elif any(f.get("compare") for f in named):
        texts = [c for f in named for c in (f.get("compare") or [])]
        out.pairs = list(dict.fromkeys(parse_pair(c) for c in texts))
        out.source = "the runs' figures.compare"
    for key, given in (
        ("reference_variant", reference_variant),
        ("ablation_teacher", ablation_teacher),
    ):
        values = {str(f[key]) for f in named if f.get(key)}
        if given:
            setattr(out, key, given)
        elif len(values) == 1:
            setattr(out, key, values.pop())
    arms, variants = sweep_requests(dirs, conf_dir)
    out.expected_arms = list(dict.fromkeys([a for p in out.pairs for a in p] + arms))
    out.arms = series_table(runs, "reward", notes, conf_dir)
    out.variants = series_table(runs, "student", notes, conf_dir)
    out.arm_order, out.variant_order = list(out.arms), list(out.variants)
    paper = list(PAPER_VARIANTS) if out.source == "the paper's pairs" and not variants else []
    out.expected_variants = list(dict.fromkeys([out.reference_variant] + paper + variants))
    return out
