"""Every file a user hands in goes through the gate, bounded before it is parsed (issue 59).

Fast guards, one per fix, each checked to fail with its fix reverted: a YAML bomb in a run's
config.yaml is refused on the parser's events (never expanded); a checkpoint's inflated
record sizes are read from its zip directory before torch inflates one; a run's tables are
checked row by row before a resume changes anything; the checkpoint a resume checked is the
one it uses; a module a checkpoint names is refused by the gate's own read. Every tool that
reads a bad file, run as a user types it (train, resume, export, play, audit, inspect, figures,
sim2sim, the robot's supervisor), refuses it in one line, with every folder unchanged, within
10 s and under 200 MB resident: before torch, mjlab or onnxruntime is imported.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
import tracemalloc
import zipfile
from dataclasses import asdict
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from march.config import ConfigError
from march.config.cli import load
from march.store.bounded_read import FileRefused, read_yaml_text
from march.store.checkpoint import (
    CheckpointError,
    keep_checked,
    load_checkpoint,
    save_atomic,
)
from march.store.gate import read_checkpoint
from march.store.resume_rules import load_saved_config
from march.store.run_tables import check_run_tables, read_table

ROOT = Path(__file__).resolve().parent.parent

LAUGHS = "".join(
    f"{c}: &{c} [{', '.join([f'*{p}'] * 9 if p else ['lol'] * 9)}]\n"
    for p, c in zip(["", *"abcdefgh"], "abcdefghi", strict=True)
)
"""A billion laughs: 9 levels of 9 aliases, ~500 bytes that expand to 9^9 strings."""


def small_config() -> str:
    return OmegaConf.to_yaml(OmegaConf.structured(load(["compute=smoke"])))


def zip_bomb(path: Path, inflated: int = 256 << 20) -> Path:
    """A student checkpoint whose one storage record is deflated from ``inflated`` zeros."""
    plain = path.with_suffix(".plain")
    torch.save({"kind": "student", "iteration": 0, "env_steps": 0, "x": torch.zeros(4)}, plain)
    with zipfile.ZipFile(plain) as src, zipfile.ZipFile(path, "w") as dst:
        for info in src.infolist():
            if info.filename.endswith("data/0"):
                record = zipfile.ZipInfo(info.filename)
                record.compress_type = zipfile.ZIP_DEFLATED
                with dst.open(record, "w", force_zip64=True) as w:
                    for _ in range(inflated >> 24):
                        w.write(bytes(1 << 24))
            else:
                dst.writestr(info, src.read(info))
    plain.unlink()
    return path


def traced(fn) -> tuple[BaseException, int]:
    """(the exception ``fn`` raised, the peak of Python's allocations while it ran)."""
    tracemalloc.start()
    try:
        fn()
    except Exception as err:  # noqa: BLE001 - returned to the test
        caught = err
    else:
        caught = None
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert caught is not None, "not refused"
    return caught, peak


# --- YAML ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, needle",
    [
        (LAUGHS, "YAML anchor (&a)"),
        ("base: &b {x: 1}\nseed: 3\n", "YAML anchor (&b)"),
        ("seed: *nowhere\n", "YAML alias (*nowhere)"),
        ("a: {x: 1}\nb:\n  <<: *a\n", "YAML alias (*a)"),  # a merge key is an alias too
        ("seed: !!python/object:os.system {}\n", "YAML tag"),
        ("seed: !custom 3\n", "YAML tag"),
        ("seed: 1\n---\nseed: 2\n", "more than one YAML document"),
        ("a: " + "[" * 100 + "]" * 100 + "\n", "nested deeper than"),
    ],
    ids=["laughs", "anchor", "alias", "merge", "python-tag", "tag", "two-docs", "deep"],
)
def test_yaml_march_never_writes_is_refused_on_its_events(tmp_path, text, needle):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(text)
    err, peak = traced(lambda: load_saved_config(run, "resume", named=[]))
    assert isinstance(err, ConfigError) and needle in str(err), err
    assert "\n" not in str(err) and str(err).startswith(f"resume={run}: ")
    assert peak < 4 << 20, peak  # the events of ~1 KB; expanded, the laughs hold gigabytes


def test_the_config_march_writes_passes_the_yaml_gate(tmp_path):
    (tmp_path / "config.yaml").write_text(small_config())
    assert load_saved_config(tmp_path, "resume", named=[]).compute.name == "smoke"
    text = read_yaml_text(tmp_path / "config.yaml", "x")
    assert OmegaConf.create(text).compute.name == "smoke"


def test_the_figures_refuse_a_yaml_bomb_in_one_line(tmp_path):
    from analysis.rundirs import load_run

    (tmp_path / "config.yaml").write_text(LAUGHS)
    err, peak = traced(lambda: load_run(tmp_path))
    assert isinstance(err, FileRefused) and "YAML anchor" in str(err) and peak < 4 << 20


# --- checkpoints: the zip directory before any record ----------------------------------------


def test_a_zip_bomb_record_is_refused_from_the_directory(tmp_path, monkeypatch):
    bomb = zip_bomb(tmp_path / "bomb.pt")
    assert bomb.stat().st_size < 1 << 20  # 256 MB of zeros in ~250 KB
    monkeypatch.setattr(torch, "load", lambda *a, **k: pytest.fail("torch read a record"))
    err, peak = traced(lambda: load_checkpoint(bomb, "student"))
    assert isinstance(err, CheckpointError) and "is compressed" in str(err), err
    assert "inflate to 268435456" in str(err) and "\n" not in str(err)
    assert peak < 4 << 20, peak


def test_a_checkpoint_torch_wrote_passes_the_record_check(tmp_path):
    payload = {"kind": "teacher", "iteration": 1, "w": torch.randn(300, 40), "config": None}
    torch.save(payload, tmp_path / "t.pt")
    assert torch.equal(load_checkpoint(tmp_path / "t.pt", "teacher")["w"], payload["w"])


# --- run tables: every row checked before anything changes -------------------------------------


HEADER = "stage,iteration,env_steps,mean_reward\n"


@pytest.mark.parametrize(
    "body, needle",
    [
        ("teacher,1,64,0.5\nteacher,abc,128,0.5\n", "line 3, column iteration: 'abc'"),
        ("teacher,1,64,0.5\nteacher,2,128,fast\n", "column mean_reward: 'fast' is not a number"),
        ("teacher,1,64\nteacher,2,128,1\n", "line 2 has 3 fields"),
        ("te acher,1,64,0.5\n", "is not a stage name"),
        ("teacher,-1,64,0.5\n", "is not a whole number"),
    ],
    ids=["iteration", "number", "fields", "stage", "negative"],
)
def test_a_bad_row_is_one_line_and_the_table_is_left_as_it_was(tmp_path, body, needle):
    from march.learn.metrics import truncate_rows

    path = tmp_path / "metrics.csv"
    path.write_text(HEADER + body)
    before = path.read_bytes()
    with pytest.raises(FileRefused, match=needle):
        check_run_tables(tmp_path)
    with pytest.raises(ConfigError, match=needle):
        truncate_rows(path, "teacher", 0)  # a resume's truncation reads through the gate too
    assert path.read_bytes() == before


def test_a_torn_last_row_is_left_out_not_refused(tmp_path):
    path = tmp_path / "metrics.csv"
    path.write_text(HEADER + "teacher,1,64,0.5\nteacher,2,12")
    table = read_table(path)
    assert [r["iteration"] for r in table.rows] == ["1"] and table.torn == "teacher,2,12"
    check_run_tables(tmp_path)


# --- the bytes checked are the bytes used --------------------------------------------------------


def test_a_resume_uses_the_checkpoint_it_checked(tmp_path):
    good = {"kind": "teacher", "iteration": 3, "w": torch.ones(2)}
    path = tmp_path / "latest.pt"
    save_atomic(good, path)
    checked = load_checkpoint(path, "teacher")
    keep_checked(path, checked)
    path.write_bytes(b"changed after the checks")  # replaced between the check and the use
    used = load_checkpoint(path, "teacher")
    assert used["iteration"] == 3 and torch.equal(used["w"], good["w"])
    with pytest.raises(CheckpointError):
        load_checkpoint(path, "teacher")  # taken once: a later read is a read
    keep_checked(path, checked)
    save_atomic({**good, "iteration": 4}, path)  # march wrote it since: forgotten
    assert load_checkpoint(path, "teacher")["iteration"] == 4


def test_the_policy_loop_loads_the_onnx_bytes_that_were_checked(bundle, tmp_path):
    import shutil

    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.runner import Sim2Sim

    copy = tmp_path / "bundle"
    shutil.copytree(bundle.parent, copy)
    loaded = Bundle.load(copy / bundle.name)
    assert hashlib.sha256(loaded.onnx_bytes).hexdigest() == loaded.spec["onnx"]["sha256"]
    (copy / bundle.name).write_bytes(b"not the graph that was checked")
    Sim2Sim(loaded, "hardware")  # loads the checked bytes, not the file by its path again


# --- the gate's own read refuses a module a checkpoint names ------------------------------------


def test_the_gate_refuses_a_module_a_checkpoint_names(tmp_path):
    name = "march_planted_by_a_checkpoint"
    (tmp_path / f"{name}.py").write_text(
        f"import pathlib\npathlib.Path({str(tmp_path / 'ran')!r}).write_text('ran')\n"
    )
    sys.path.insert(0, str(tmp_path))
    try:
        saved = asdict(load(["compute=smoke"]))
        saved["extra_modules"] = [name]
        payload = {"kind": "teacher", "iteration": 0, "env_steps": 0, "config": saved}
        torch.save(payload, tmp_path / "t.pt")
        with pytest.raises(ConfigError, match=f"names module '{name}'"):
            read_checkpoint(str(tmp_path / "t.pt"), "teacher", named=[])
    finally:
        sys.path.remove(str(tmp_path))
    assert not (tmp_path / "ran").exists() and name not in sys.modules


def test_the_gate_refuses_an_interpolation_in_a_checkpoints_config(tmp_path, monkeypatch):
    monkeypatch.setenv("MARCH_PLANTED", "resolved")
    saved = asdict(load(["compute=smoke"]))
    saved["reward"]["label"] = "${oc.env:MARCH_PLANTED}"
    payload = {"kind": "teacher", "iteration": 0, "env_steps": 0, "config": saved}
    torch.save(payload, tmp_path / "t.pt")
    with pytest.raises(ConfigError, match=r"reward.label holds a '\$\{...\}' interpolation"):
        read_checkpoint(str(tmp_path / "t.pt"), "teacher", named=[])


# --- the real command: one line, the directory unchanged ---------------------------------------


def _tree_hash(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def bad_run(run: Path, bad: str) -> Path:
    """A finished run directory holding one bad file: ``laughs`` (config.yaml a billion
    laughs), ``zip-bomb`` (teacher/latest.pt) or ``metrics-row`` (an iteration ``abc``)."""
    (run / "teacher").mkdir(parents=True)
    (run / "config.yaml").write_text(LAUGHS if bad == "laughs" else small_config())
    (run / "status.json").write_text('{"state": "done", "time": 1.0, "stage": "all"}')
    (run / "train.log").write_text("")
    (run / "metrics.csv").write_text(
        HEADER + ("teacher,abc,64,0.5\n" if bad == "metrics-row" else "teacher,1,64,0.5\n")
    )
    if bad == "zip-bomb":
        zip_bomb(run / "teacher" / "latest.pt")
    return run


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory) -> Path:
    """One folder of bad inputs: three bad runs, a zip-bomb student checkpoint, and a bundle
    whose deploy.json gives a key twice (refused by the strict JSON read before anything else
    of the bundle is looked at, so no exported ONNX is needed)."""
    root = tmp_path_factory.mktemp("bad_files")
    for bad in ("laughs", "zip-bomb", "metrics-row"):
        bad_run(root / bad, bad)
    (root / "s" / "student").mkdir(parents=True)
    zip_bomb(root / "s" / "student" / "latest.pt")
    (root / "dup").mkdir()
    (root / "dup" / "student.onnx").write_bytes(b"not read")
    (root / "dup" / "student.deploy.json").write_text('{"format": 3, "format": 3}')
    return root


REFUSALS = {
    # case: (the command after `python`, with {root} for the fixture's folder; the words of the
    # one line; what the line starts with)
    "train-resume-laughs": (
        "-m march.train resume={root}/laughs",
        "YAML anchor",
        "resume={root}/laughs: ",
    ),
    "train-resume-zip": (
        "-m march.train resume={root}/zip-bomb",
        "is compressed",
        "resume={root}/zip-bomb: ",
    ),
    "train-resume-metrics": (
        "-m march.train resume={root}/metrics-row",
        "'abc'",
        "resume={root}/metrics-row: ",
    ),
    "train-new-run-laughs": (
        "-m march.train hydra.run.dir={root}/laughs",
        "YAML anchor",
        "hydra.run.dir={root}/laughs: ",
    ),
    "train-eval-zip": (
        "-m march.train stage=eval student_ckpt={root}/s/student/latest.pt",
        "is compressed",
        "student_ckpt={root}/s/student/latest.pt: ",
    ),
    "export-zip": (
        "-m march.export student_ckpt={root}/s/student/latest.pt out={root}/out",
        "is compressed",
        "student_ckpt={root}/s/student/latest.pt: ",
    ),
    "play-zip": (
        "-m march.play student_ckpt={root}/s/student/latest.pt",
        "is compressed",
        "student_ckpt={root}/s/student/latest.pt: ",
    ),
    "audit-zip": (
        "-m march.audit rewards teacher_ckpt={root}/s/student/latest.pt out={root}/a.json",
        "is compressed",
        "teacher_ckpt={root}/s/student/latest.pt: ",
    ),
    "audit-options-zip": (  # audit.* values are checked after the file gate, torch-free before
        "-m march.audit reference audit.stance=heel_off teacher_ckpt={root}/s/student/latest.pt"
        " out={root}/r.json",
        "is compressed",
        "teacher_ckpt={root}/s/student/latest.pt: ",
    ),
    "inspect-laughs": ("-m march.inspect run {root}/laughs", "YAML anchor", "{root}/laughs"),
    "inspect-zip": ("-m march.inspect run {root}/zip-bomb", "is compressed", "{root}/zip-bomb"),
    "figures-metrics": ("analysis/figures.py {root}/metrics-row", "'abc'", "figures.py: "),
    "sim2sim-dup": ("-m march.sim2sim onnx={root}/dup/student.onnx", "given twice", "{root}"),
    "supervisor-dup": (
        "-m march.robot supervisor bundle={root}/dup interface=lo",
        "given twice",
        "{root}",
    ),
}

RUN_AND_MEASURE = (
    "import json, os, resource, subprocess, sys, time\n"
    "path = os.pathsep.join(p for p in (sys.argv[1], os.environ.get('PYTHONPATH')) if p)\n"
    "t = time.perf_counter()\n"
    "r = subprocess.run([sys.executable, *sys.argv[2:]], capture_output=True, text=True,"
    " timeout=60, env={**os.environ, 'PYTHONPATH': path})\n"
    "print(json.dumps({'rc': r.returncode, 'stderr': r.stderr, 'stdout': r.stdout,"
    " 'wall_s': time.perf_counter() - t,"
    " 'peak_mb': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}))\n"
)
"""``python -c RUN_AND_MEASURE <hook folder> <command>``: the command run as a user types it,
with the hook folder first on its ``PYTHONPATH``; a fresh process per case, so that its
children's peak resident size (``ru_maxrss``, KB on Linux) is the tool's alone."""

SEEN_MODULES = (
    "import atexit, sys\n"
    "if sys.argv[0] != '-c':\n"
    "    atexit.register(lambda: sys.stdout.write('modules: ' + ','.join(m for m in"
    " ('torch', 'mjlab', 'onnxruntime') if m in sys.modules) + '\\n'))\n"
)
"""The hook folder's ``sitecustomize``, run by Python before the tool: at exit, the heavy
modules the process had imported, on stdout. Not in a ``python -c`` child the tool starts:
glfw's version probe (imported with mjlab's viewer) evals such a child's stdout, and the line
would crash it instead of showing which module was imported."""


@pytest.mark.parametrize("case", list(REFUSALS))
def test_every_tool_refuses_a_bad_file_in_one_line_without_torch(bad_files, tmp_path, case):
    """Each tool, run as a user types it, refuses each bad file it reads in one line (exit 2)
    within 10 s and under 200 MB resident, before torch, mjlab or onnxruntime is imported
    (``import torch`` alone is ~250 MB), and leaves every folder as it was (issue 59)."""
    import json

    command, words, start = (x.format(root=bad_files) for x in REFUSALS[case])
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(SEEN_MODULES)
    before = _tree_hash(bad_files)
    out = subprocess.run(
        [sys.executable, "-c", RUN_AND_MEASURE, str(hook), *command.split()],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    lines = res["stderr"].splitlines()
    assert res["rc"] == 2 and len(lines) == 1, res["stderr"][-2000:]
    line = lines[0].removeprefix("error: ")
    assert line.startswith(start) and words in line, line
    assert res["peak_mb"] < 200, res["peak_mb"]
    assert "modules: \n" in res["stdout"], res["stdout"][-500:]  # none of them imported
    assert res["wall_s"] < 10, res["wall_s"]
    assert _tree_hash(bad_files) == before  # nothing written, moved or removed


@pytest.mark.parametrize(
    "tool",
    [
        "export",
        pytest.param("play", marks=pytest.mark.slow),
        pytest.param("audit", marks=pytest.mark.slow),
        pytest.param("eval", marks=pytest.mark.slow),
        pytest.param("inspect-run", marks=pytest.mark.slow),
    ],
)
def test_every_tool_refuses_a_zip_bomb_before_the_simulator(tmp_path, tool):
    """The record check runs before the term check imports mjlab (since the file checks run
    before torch is imported each takes ~1 s; the fast table above covers these tools too)."""
    (tmp_path / "run" / "student").mkdir(parents=True)
    bomb = zip_bomb(tmp_path / "run" / "student" / "latest.pt")
    args = {
        "export": ["march.export", f"student_ckpt={bomb}", f"out={tmp_path / 'out'}"],
        "play": ["march.play", f"student_ckpt={bomb}"],
        "audit": ["march.audit", "rewards", f"teacher_ckpt={bomb}", f"out={tmp_path / 'a.json'}"],
        "eval": [
            "march.train",
            "stage=eval",
            f"student_ckpt={bomb}",
            f"hydra.run.dir={tmp_path / 'e'}",
        ],
        "inspect-run": ["march.inspect", "run", str(tmp_path / "run")],
    }[tool]
    code = (
        "import runpy, sys\n"
        f"sys.argv = {args!r}\n"
        "try:\n"
        "    runpy.run_module(sys.argv[0], run_name='__main__', alter_sys=True)\n"
        "finally:\n"
        "    print('mjlab' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 2 and len(out.stderr.splitlines()) == 1, out.stderr
    assert "is compressed" in out.stderr and out.stdout.split()[-1] == "False", out.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # nothing written
