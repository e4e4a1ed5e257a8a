"""Turn MARCH run directories into the paper's figures and tables.

Usage::

    python analysis/figures.py RUN_OR_SWEEP_DIR [MORE_DIRS ...] [--out DIR]
        [--target-distance 2.0] [--smooth 20] [--se-mode seeds|pooled]

Runs are found recursively: a run is a directory holding ``config.yaml`` (the resolved config)
or ``.hydra/config.yaml``; a Hydra sweep directory (``multirun.yaml`` + ``0/``, ``1/``, ...) is
searched, never taken as a run. Every run found is listed in ``runs.md``/``runs.csv`` with its
state and row counts; failed or incomplete runs are named there and on stdout, and the figures
still use whatever rows they have.

Every comparison is read from evaluation rows (``eval.csv``: each policy rolled out on the fixed
evaluation set under one protocol for every arm). Written into ``--out`` (default
``<first dir>/figures``):

* ``baseline.{png,pdf}`` -- distance, |torque|, |angular jerk| and success vs distillation
  iteration, clf (blue) vs modelfree (red), student variant ``full``; ``eval.csv`` rows
  ``stage == "student"``; error bars 4 x SE (the paper's Fig. 4).
* ``sample_efficiency.{png,pdf}`` -- both teachers' distance and success on the fixed stone
  evaluation set vs teacher iteration, and distance vs teacher env steps; ``eval.csv`` rows
  ``stage == "teacher"`` (every ``teacher.eval_interval`` iterations); bars 1 x SE; the target
  line is the claims' (``--threshold-fraction`` x the better final distance of the compared
  pair, controls left out) unless ``--target-distance`` is given.
  ``sample_efficiency.csv``: the first teacher iteration / env steps at which each arm's
  seed-mean evaluation distance reaches the target, per arm and per run, and clf vs modelfree
  as (clf - modelfree) / modelfree.
* ``ablation.{png,pdf}`` -- the paper's ablation metric, the teacher's reward per control step on
  student rollouts (``mean_reward_per_step``), with distance and success beside it (standing
  still can score on the first, not on these) vs distillation iteration for the clf teacher's
  students full / no_transformer / no_mdn; ``eval.csv`` rows ``stage == "student"``; bars
  1 x SE.
* ``teacher_curves.{png,pdf}`` -- a training DIAGNOSTIC, not a comparison: ``metrics.csv``
  teacher rows (training rollouts, each arm on its own curriculum), moving average ``--smooth``.
* ``final_metrics.{md,csv}`` -- per reward x student variant the final evaluation
  (``summary.json`` of complete runs, the run's last student evaluation), mean +- SE, and the
  paper's relative differences: (clf - modelfree) / modelfree for student full, (variant - full)
  / full for the ablation, written like ``torque -12%``; also printed on stdout.
* ``figure_data.csv`` -- every plotted point (figure, panel, x_name, series, x, y, se, yerr, n),
  the standing floors included (``x_name`` ``standing_floor``).

The standing floor (issue 56): every evaluation row records the zero action's distance on the
same rollouts (``floor_distance_m``). Every distance panel draws it as a dashed line (one black
line when all series share it, else one per series in its colour; the training diagnostic's is
the teacher evaluations' floor, so labelled), and every distance printed has it beside it
(stdout, a ``standing floor`` column in final_metrics and sample_efficiency.csv, a "Standing
floor" section in claims.md). Runs from before it: "no standing floor in these runs".
* ``runs.{md,csv}`` -- every run found, its config keys, state, row counts and problems.

A run without the rows a figure needs (an old run without teacher evaluations, a teacher-only
run) is named on stdout and in a grey note above the panel (never over its data); a figure with
no rows at all is skipped with a note. ``claims.{md,csv}`` -- the paper's claims with intervals,
the seeds behind each, verdicts and what was not compared (analysis/claims.py). ``eval.csv`` files with fewer columns (older versions) load as they are.

Combining several seeds (``--se-mode``): with ``seeds`` (default) the mean is the mean of the
per-seed means and the standard error is the SE *across seeds*, std(ddof=1)/sqrt(n); a point
backed by a single run keeps that run's own SE over rollouts (``se_*`` columns). With ``pooled``
the SE is sqrt(sum se_i^2)/n, i.e. rollout noise only. The training diagnostic (no per-run SE)
uses the across-seed SE.

This script reads files only: it imports pandas, numpy, matplotlib and omegaconf, never the
simulator or the ``march`` package.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the ``analysis`` package importable
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import pandas as pd  # noqa: E402

from analysis.aggregate import (  # noqa: E402
    ablation_data,
    baseline_data,
    sample_efficiency,
    sample_efficiency_data,
    teacher_refused,
    teacher_training_data,
)
from analysis.arms import choose, parse_pair  # noqa: E402
from analysis.claims import ClaimsInput, claims, claims_markdown  # noqa: E402
from analysis.final_table import final_table  # noqa: E402
from analysis.groups import DuplicateRunsError, group_runs  # noqa: E402
from analysis.plotting import (  # noqa: E402
    ABLATION,
    BASELINE,
    POINT_COLUMNS,
    SAMPLE_EFFICIENCY,
    eval_points,
    floor_points,
    plot_eval_figure,
    plot_teacher_training,
    teacher_points,
)
from analysis.reports import report, write_tables  # noqa: E402
from analysis.rundirs import discover, runs_frame  # noqa: E402
from march.store.bounded_read import FileRefused  # noqa: E402


def _cat(*frames: pd.DataFrame) -> pd.DataFrame:
    """Point tables one after another (empty ones left out: pandas warns on them)."""
    kept = [f for f in frames if not f.empty]
    return pd.concat(kept, ignore_index=True) if kept else frames[0]


def analyze(
    dirs: list[Path],
    out: Path,
    target: float | None = None,
    window: int = 20,
    mode: str = "seeds",
    compare: list[str] | None = None,
    reference_variant: str | None = None,
    ablation_teacher: str | None = None,
    allow_duplicates: bool = False,
    threshold_fraction: float = 0.9,
) -> dict:
    """Load runs, write figures and tables into ``out``; returns what was computed.

    ``compare``: arm pairs ``A:B`` (default: the runs' ``figures.compare``, else clf:modelfree);
    ``reference_variant`` / ``ablation_teacher``: the ablation's reference (full) and teacher
    (clf). A malformed pair raises ValueError, two runs of one group with the same seed
    DuplicateRunsError (unless ``allow_duplicates``: the newest is kept), before anything is
    written."""
    found = discover(dirs)
    notes: list[str] = []
    written: list[Path] = []
    if not found:
        return {"runs": found, "notes": notes, "written": written}
    groups = group_runs(found, allow_duplicates, notes)
    kept = {id(r) for members in groups.values() for r in members}
    runs = [r for r in found if id(r) in kept]
    comp = choose(runs, dirs, compare, reference_variant, ablation_teacher, notes)
    out.mkdir(parents=True, exist_ok=True)
    all_points = []
    axes_notes: dict[str, dict] = {}

    base = baseline_data(runs, mode, notes, comp)
    if base:
        pts = _cat(eval_points(BASELINE, base), floor_points("baseline", "distance_m", base.floors))
        axes_notes["baseline"] = plot_eval_figure(BASELINE, pts, base, mode, out, written, comp)
        all_points.append(pts)
    else:
        notes.append(
            f"skip baseline: no eval.csv student rows of a '{comp.reference_variant}' student "
            "in any run"
        )

    se_curves = sample_efficiency_data(runs, mode, notes, comp)
    eff = sample_efficiency(runs, se_curves, target, notes, comp, threshold_fraction)
    if not eff.empty:
        target = float(eff["target_distance_m"].iloc[0])
    if se_curves:
        pts = eval_points(SAMPLE_EFFICIENCY, se_curves)
        floors = floor_points(SAMPLE_EFFICIENCY.stem, "distance_m", se_curves.floors)
        pts = _cat(pts, floors)
        axes_notes["sample_efficiency"] = plot_eval_figure(
            SAMPLE_EFFICIENCY, pts, se_curves, mode, out, written, comp, target, eff
        )
        all_points.append(pts)
    else:
        notes.append(
            "skip sample_efficiency: no eval.csv teacher rows in any run (runs from before "
            "teacher evaluations existed have none; teacher_curves is a training diagnostic only)"
        )

    abl = ablation_data(runs, mode, notes, comp)
    if abl:
        pts = _cat(eval_points(ABLATION, abl), floor_points("ablation", "distance_m", abl.floors))
        axes_notes["ablation"] = plot_eval_figure(ABLATION, pts, abl, mode, out, written, comp)
        all_points.append(pts)
    else:
        notes.append(f"skip ablation: no eval.csv student rows of a {comp.ablation_teacher} run")

    teach = teacher_training_data(runs, window, notes, comp)
    if teach:
        pts = teacher_points(teach)
        refused = teacher_refused(runs, comp)[1]
        # the arms' floors on their teacher evaluations (training rollouts have none)
        floors = {k: f for k, f in se_curves.floors.items() if k in teach}
        axes_notes["teacher_curves"] = {
            "mean_distance_m": plot_teacher_training(
                teach, pts, window, out, written, notes, comp, refused, floors
            )
        }
        pts = _cat(pts, floor_points("teacher_curves", "mean_distance_m", floors))
        all_points.append(pts)
    else:
        notes.append("skip teacher_curves: no metrics.csv teacher rows with values in any run")

    table = final_table(runs, mode, notes, comp)
    pairs = comp.pairs[0] if comp.pairs else ("clf", "modelfree")
    # Claims read complete runs only (a crashed run's rows stop early); the others are named.
    partial = [r.label for members in groups.values() for r in members if not r.complete]
    if partial:
        notes.append("claims: incomplete runs left out: " + ", ".join(partial))
    complete = {k: [r for r in v if r.complete] for k, v in groups.items()}
    claims_input = ClaimsInput(
        {k: v for k, v in complete.items() if v},
        arm=pairs[0],
        reference=pairs[1],
        full=comp.reference_variant,
        ablation_teacher=comp.ablation_teacher,
        threshold_fraction=threshold_fraction,
    )
    claim_rows = claims(claims_input, notes)
    claim_rows.to_csv(out / "claims.csv", index=False)
    (out / "claims.md").write_text(
        claims_markdown(claim_rows, claims_input.refused, claims_input.floors)
    )
    written += [out / "claims.csv", out / "claims.md"]
    if table.empty:
        notes.append("skip final_metrics: no complete run with a student summary.json")
    listing = runs_frame(runs)
    points = (
        pd.concat(all_points, ignore_index=True)
        if all_points
        else pd.DataFrame(columns=POINT_COLUMNS)
    )
    write_tables(out, listing, table, eff, points, mode, written, comp)
    return {
        "runs": runs,
        "comparisons": comp,
        "notes": notes,
        "written": written,
        "baseline": base,
        "sample_efficiency_curves": se_curves,
        "sample_efficiency": eff,
        "ablation": abl,
        "teacher": teach,
        "points": points,
        "axes_notes": axes_notes,
        "final": table,
        "listing": listing,
        "claims": claim_rows,
        "refused": claims_input.refused,
    }


class _OneLineParser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse prints its usage block too: one line instead
        print(f"figures.py: {message} (--help lists the options)", file=sys.stderr)
        raise SystemExit(2)


def main(argv: list[str] | None = None) -> int:
    ap = _OneLineParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="run dirs or Hydra sweep dirs")
    ap.add_argument("--out", type=Path, default=None, help="output dir (default <first>/figures)")
    ap.add_argument(
        "--threshold-fraction",
        type=float,
        default=0.9,
        help="sample efficiency: the distance to reach, as a fraction of the better arm's final "
        "teacher evaluation distance (default 0.9)",
    )
    ap.add_argument(
        "--target-distance",
        type=float,
        default=None,
        help="sample efficiency: an absolute distance [m] to reach instead (figures only; the "
        "claims use --threshold-fraction)",
    )
    ap.add_argument(
        "--allow-duplicates",
        action="store_true",
        help="two runs of one group with the same seed: keep the newest (said in the output) "
        "instead of refusing",
    )
    ap.add_argument(
        "--smooth",
        type=int,
        default=20,
        help="moving-average window [iterations] of the teacher_curves training diagnostic",
    )
    ap.add_argument(
        "--se-mode",
        choices=["seeds", "pooled"],
        default="seeds",
        help="how SEs of several seeds combine (default seeds)",
    )
    ap.add_argument(
        "--compare",
        action="append",
        metavar="ARM:REFERENCE",
        help="compare reward arm ARM with REFERENCE, (ARM - REFERENCE) / REFERENCE, student = "
        "the reference variant; repeatable (default: the runs' figures.compare, else "
        "clf:modelfree)",
    )
    ap.add_argument(
        "--reference-variant",
        default=None,
        help="the student variant the arms are compared with and the ablation is relative to "
        "(default: the runs' figures.reference_variant, else full)",
    )
    ap.add_argument(
        "--ablation-teacher",
        default=None,
        help="the reward arm whose students form the ablation (default: the runs' "
        "figures.ablation_teacher, else clf)",
    )
    ap.add_argument(
        "--terms",
        action="store_true",
        help="per-term training curves of each run instead (analysis/term_curves.py)",
    )
    args = ap.parse_args(argv)
    for pair in args.compare or []:
        try:
            parse_pair(pair)
        except ValueError as err:
            print(f"figures.py: {err}", file=sys.stderr)
            return 2
    for d in args.dirs:
        if not d.is_dir():
            print(
                f"figures.py: {d} is not a directory (expected a run dir or a sweep dir)",
                file=sys.stderr,
            )
            return 2
    out = args.out if args.out is not None else args.dirs[0] / "figures"
    if args.terms:  # reward/<term>, termination/<term>, levels, loss/<part> per run
        from analysis.term_curves import draw

        try:
            lines = draw(discover(args.dirs), out, smooth=1)
        except FileRefused as err:  # a run file march did not write (march.store.bounded_read)
            print(f"figures.py: {err}", file=sys.stderr)
            return 2
        print("\n".join(lines) if lines else "figures.py: no runs found", file=sys.stdout)
        return 0 if lines else 2
    if not 0.0 < args.threshold_fraction <= 1.0:
        print("figures.py: --threshold-fraction must be in (0, 1]", file=sys.stderr)
        return 2
    try:
        res = analyze(
            args.dirs,
            out,
            args.target_distance,
            args.smooth,
            args.se_mode,
            args.compare,
            args.reference_variant,
            args.ablation_teacher,
            args.allow_duplicates,
            args.threshold_fraction,
        )
    except (DuplicateRunsError, FileRefused) as err:
        print(f"figures.py: {err}", file=sys.stderr)
        return 2
    if not res["runs"]:
        where = ", ".join(str(d) for d in args.dirs)
        print(
            f"figures.py: no runs found under {where} (expected a run dir with config.yaml or "
            ".hydra/config.yaml, or a sweep dir with multirun.yaml and job subdirs 0/, 1/, ...)",
            file=sys.stderr,
        )
        return 2
    print(report(res, out), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
