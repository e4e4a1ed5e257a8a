"""mkdocs hook: pages generated from the code and the decision log when the site is built.

- ``reference/configuration.md``: every config field (type, default, unit, allowed values, its
  docstring) and every ``conf/`` group option with its YAML (:mod:`march.config.field_docs`);
- ``reference/options.md``: every option a run can name (reward terms with parameters and needs,
  rewards, experiments, student parts and variants, sweeps), the output of
  ``python -m march.inspect list`` (:mod:`march.config.listing`), so no page lists them by hand;
- ``reference/tools.md``: each ``python -m march.<tool>`` and analysis script, its docstring and
  usage line(s), read from the source (no tool is imported: no simulator starts);
- ``decisions/``: ``docs/decisions.md`` (the file engineers append to) split into one record per
  decision (each ``- **Title.**`` bullet; a section's text before its first bullet is a record of
  its own), numbered in file order for reading, each page's address taken from its title (not
  its number) so that a record inserted anywhere moves no other page; old ones keep
  theirs, and an index grouped by the log's ``##`` sections.

Nothing generated is committed; ``tests/test_docs.py`` builds the same pages.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

TOOLS = {
    "march.train": "march/train.py",
    "march.inspect": "march/inspect.py",
    "march.play": "march/play.py",
    "march.bench": "march/bench/command.py",
    "march.viz": "march/viz/views.py",
    "march.export": "march/export/bundle.py",
    "march.sim2sim": "march/sim2sim/command_line.py",
    "march.robot": "march/robot/robot_command.py",
}
"""Each ``python -m`` tool and the file holding its command line (docstring, ``*USAGE``)."""
SCRIPTS = ("analysis/figures.py", "analysis/bench_figure.py")
"""argparse scripts: their ``--help`` is the reference."""


def _usages(tree: ast.Module) -> list[str]:
    out = []
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id.endswith("USAGE") for t in node.targets
        ):
            try:
                out.append(str(ast.literal_eval(node.value)))
            except ValueError:
                continue
    for node in ast.walk(tree):  # usage="..." given inline to run_tool
        if isinstance(node, ast.keyword) and node.arg == "usage":
            if isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
                out.append(node.value.value)
    return list(dict.fromkeys(out))


def tools_markdown() -> str:
    lines = [
        "# Command-line tools",
        "",
        "Generated when the site is built, from each tool's source: its docstring and usage",
        "line. Every `python -m march.<tool>` also takes any config key as `key=value`",
        "([configuration reference](configuration.md)); a bad argument is one line on stderr and",
        "exit code 2, before anything is built.",
        "",
    ]
    for tool, rel in TOOLS.items():
        tree = ast.parse((ROOT / rel).read_text())
        doc = ast.get_docstring(tree) or ""
        lines += [f"## `python -m {tool}`", "", f"Source: `{rel}`", ""]
        for usage in _usages(tree):
            lines += ["```text", usage, "```", ""]
        if doc:
            lines += ["```text", doc, "```", ""]
    for rel in SCRIPTS:
        proc = subprocess.run(
            [sys.executable, str(ROOT / rel), "--help"],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=ROOT,
        )
        if proc.returncode != 0:
            raise RuntimeError(f"{rel} --help failed: {proc.stderr.strip()[-300:]}")
        lines += [f"## `python {rel}`", "", "```text", proc.stdout.rstrip(), "```", ""]
    return "\n".join(lines) + "\n"


def _sections(text: str) -> list[tuple[str, list[str]]]:
    """(title, lines) per ``## `` section; the text before the first one is 'Early decisions'."""
    out: list[tuple[str, list[str]]] = [("Early decisions", [])]
    fence = False
    for line in text.splitlines():
        if line.startswith("```"):
            fence = not fence
        if not fence and line.startswith("## "):
            out.append((line[3:].strip(), []))
        elif not fence and line.startswith("# ") and len(out) == 1 and not out[0][1]:
            continue  # the log's own title
        else:
            out[-1][1].append(line)
    return [(t, b) for t, b in out if any(x.strip() for x in b)]


_BOLD = re.compile(r"^- \*\*(.+?)\*\*", flags=re.S)
"""A decision bullet's bold title (it may run over two lines)."""


def _slug(text: str) -> str:
    s = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return s[:50].rstrip("-") or "decision"


def decision_records(text: str) -> list[dict[str, str]]:
    """One record per decision bullet (and per section intro), in file order."""
    records = []
    for section, body in _sections(text):
        chunks: list[list[str]] = [[]]
        fence = False
        for line in body:
            if line.startswith("```"):
                fence = not fence
            if not fence and line.startswith("- **"):
                chunks.append([])
            chunks[-1].append(line)
        for k, chunk in enumerate(chunks):
            if not any(x.strip() for x in chunk):
                continue
            text = "\n".join([chunk[0]] + [x[2:] if x.startswith("  ") else x for x in chunk[1:]])
            m = _BOLD.match(text) if k else None
            if m:
                title = " ".join(m.group(1).split()).rstrip(".:")
                content = text[m.end() :].lstrip(" .:").strip()
            else:
                title = f"{section}: overview"
                content = "\n".join(chunk).strip()
            records.append({"section": section, "title": title, "content": content})
    # Addresses come from the record's own words, never its position: a record inserted above
    # (or a union merge of two sessions' appends) moves no other page. A title used twice gets
    # its section's slug in front; a third use, its order among the same title and section.
    seen: dict[str, int] = {}
    titles = [_slug(r["title"]) for r in records]
    for n, (rec, slug) in enumerate(zip(records, titles, strict=True), start=1):
        if titles.count(slug) > 1:
            slug = f"{_slug(rec['section'])}--{slug}"
        seen[slug] = seen.get(slug, 0) + 1
        rec["file"] = f"{slug}.md" if seen[slug] == 1 else f"{slug}-{seen[slug]}.md"
        rec["number"] = str(n)
    return records


def _fix_links(text: str) -> str:
    """Links written from docs/ point one level up from docs/decisions/."""
    return re.sub(r"\]\((?!https?:|#|/)([^)]+)\)", r"](../\1)", text)


def decision_pages(text: str) -> dict[str, str]:
    """{path under docs/: markdown} of the records and their index."""
    recs = decision_records(text)
    pages = {}
    index = [
        "# Decisions",
        "",
        "Where the paper and the SPEC are silent, march decided; each decision is a short record.",
        f"{len(recs)} records, generated when the site is built from `docs/decisions.md` (the log",
        "engineers append to; [the whole log](../decisions.md)), grouped by its sections.",
        "",
    ]
    section = None
    for rec in recs:
        if rec["section"] != section:
            section = rec["section"]
            index += ["", f"## {section}", ""]
        index.append(f"- [{rec['number']}. {rec['title']}]({rec['file']})")
        pages[f"decisions/{rec['file']}"] = (
            f"# {rec['number']}. {rec['title']}\n\n"
            f"*{rec['section']}* · [all decisions](index.md)\n\n"
            f"{_fix_links(rec['content'])}\n"
        )
    pages["decisions/index.md"] = "\n".join(index) + "\n"
    return pages


PAPER = [
    # (stage, the paper's parameter, the paper's value, march's config key)
    ("scale", "Parallel environments", "4,096", "compute.num_envs"),
    ("teacher", "Network: MLP actor-critic hidden units", "(512, 256, 128)", "teacher.hidden_dims"),
    ("teacher", "Activation", "ELU", "teacher.activation"),
    ("teacher", "Actor initial std", "1.0", "teacher.init_std"),
    ("teacher", "Learning rate", "5e-5", "teacher.learning_rate"),
    ("teacher", "LR schedule", "adaptive", "teacher.schedule"),
    ("teacher", "PPO epochs", "5", "teacher.num_learning_epochs"),
    ("teacher", "Mini-batches", "4", "teacher.num_mini_batches"),
    ("teacher", "Clip parameter", "0.2", "teacher.clip_param"),
    ("teacher", "Value loss coefficient", "1.0", "teacher.value_loss_coef"),
    ("teacher", "Entropy coefficient", "0.008", "teacher.entropy_coef"),
    ("teacher", "Discount factor gamma", "0.99", "teacher.gamma"),
    ("teacher", "GAE lambda", "0.95", "teacher.lam"),
    ("teacher", "Target KL", "0.01", "teacher.desired_kl"),
    ("teacher", "Max gradient norm", "1.0", "teacher.max_grad_norm"),
    ("teacher", "Rollout length [steps/env]", "24", "teacher.num_steps_per_env"),
    ("teacher", "Training iterations", "10000", "teacher.max_iterations"),
    ("student", "Student network", "CNN-Transformer-MDN", "student.variant"),
    ("student", "Activation", "ELU", "student.activation"),
    ("student", "MDN modes", "2", "student.num_modes"),
    ("student", "Minimum std", "1e-3", "student.min_std"),
    ("student", "Log-std range", "[-3, 2]", "student.log_std_min"),
    ("student", "Optimizer, learning rate", "Adam, 5e-4", "distill.learning_rate"),
    ("student", "Distillation epochs", "10", "distill.num_learning_epochs"),
    ("student", "Gradient length", "2", "distill.gradient_length"),
    ("student", "Teacher samples", "8", "distill.teacher_samples"),
    ("student", "Teacher std scale", "0.1", "distill.teacher_std_scale"),
    ("student", "Max gradient norm", "2.0", "distill.max_grad_norm"),
    ("student", "Rollout length [steps/env]", "120", "distill.num_steps_per_env"),
    ("student", "Training iterations", "1500", "distill.max_iterations"),
    ("DR", "Friction coefficient", "U(0.5, 1.25)", "dr.friction"),
    ("DR", "Link mass", "U(0.9, 1.2) x default", "dr.link_mass_scale"),
    ("DR", "Base additional mass [kg]", "U(-1.0, 3.0)", "dr.base_added_mass_kg"),
    ("DR", "Encoder bias [rad]", "U(-0.015, 0.015)", "dr.encoder_bias_rad"),
    ("DR", "Base CoM offset x, y, z [m]", "+-0.025, +-0.05, +-0.05", "dr.base_com_offset_m"),
    ("DR", "Motor effort limits", "U(0.85, 1.1) x default", "dr.effort_limit_scale"),
    ("DR", "Joint damping", "U(0.75, 1.25) x default", "dr.joint_damping_scale"),
    ("DR", "Joint friction", "U(0.0, 0.04)", "dr.joint_friction"),
    ("DR", "Push interval [s]", "10-15", "dr.push_interval_s"),
    ("DR", "Push linear velocity x, y [m/s]", "U(-1, 1)", "dr.push_lin_vel"),
    ("DR", "Push angular velocity [rad/s]", "U(-0.4, 0.4)", "dr.push_ang_vel"),
    ("DR", "Control delay [ms]", "U(0, 20)", "dr.control_delay_ms"),
    ("DR", "Depth camera translation [m]", "U(-0.025, 0.025) per axis", "dr.camera_pos_m"),
    ("DR", "Depth camera rotation r, p, y [deg]", "+-2.5, +-3.0, +-2.5", "dr.camera_rot_deg"),
    ("DR", "Depth camera FOV [deg]", "U(-2.0, 2.0)", "dr.camera_fov_deg"),
    ("DR", "Pixel dropout", "5%", "depth.dropout"),
    ("DR", "Depth noise sigma", "0.1 x depth", "depth.noise_scale"),
]
"""The paper's tables (simulation, domain randomization, training hyperparameters) and the
config key that holds march's value."""


def paper_markdown() -> str:
    """The paper's parameters beside march's, march's read from the composed gpu preset."""
    from march.config.cli import load

    cfg = load(["compute=gpu", "compute.device=cpu"])
    lines = [
        "# The paper's parameters beside march's",
        "",
        "The paper's values are copied from its tables (simulation and infrastructure, domain",
        "randomization, training hyperparameters); march's are read, when the site is built, from",
        "the composed config of the paper-scale preset (`compute=gpu reward=clf student=full`),",
        "so a changed default shows here. Differences of form, not of value, are explained on",
        "[the method page](../method.md); each key is in the",
        "[configuration reference](configuration.md).",
        "",
        "| stage | parameter | paper | march | key |",
        "|---|---|---|---|---|",
    ]
    for stage, name, paper, key in PAPER:
        value: object = cfg
        for part in key.split("."):
            value = getattr(value, part)
        if key == "student.log_std_min":
            value = [cfg.student.log_std_min, cfg.student.log_std_max]
        shown = str(list(value) if isinstance(value, (list, tuple)) else value)
        lines.append(f"| {stage} | {name} | {paper} | `{shown}` | `{key}` |")
    return "\n".join(lines) + "\n"


def options_markdown() -> str:
    """``python -m march.inspect list``'s text as a page (the registries, read at build time)."""
    from march.config.listing import collect, render

    return (
        "# Options: terms, rewards, experiments, student parts, variants, sweeps\n\n"
        "Every option a run can name, read from the registries and config groups when this site "
        "was built. `python -m march.inspect list` prints the same, and with "
        "`extra_modules=[...]` / `hydra.searchpath=[...]` it includes your own terms, parts "
        "and options ([Extending](../extending.md)).\n\n"
        f"```text\n{render(collect())}\n```\n"
    )


def generated_pages(docs_dir: Path) -> dict[str, str]:
    from march.config import MarchConfig
    from march.config.field_docs import render_markdown

    pages = {
        "reference/configuration.md": render_markdown(MarchConfig),
        "reference/tools.md": tools_markdown(),
        "reference/options.md": options_markdown(),
        "reference/paper-vs-march.md": paper_markdown(),
    }
    pages.update(decision_pages((docs_dir / "decisions.md").read_text()))
    return pages


def on_files(files, config):  # noqa: ANN001 - mkdocs' hook signature
    from mkdocs.structure.files import File

    for path, content in generated_pages(Path(config["docs_dir"])).items():
        files.append(File.generated(config, path, content=content))
    return files
