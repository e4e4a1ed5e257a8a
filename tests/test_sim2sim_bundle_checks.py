"""A deploy bundle is checked before use: every key, every type, files confined to the bundle.

The smoke student's bundle is copied and its ``deploy.json`` broken in generated ways: every key
of the file removed in turn (a sample of leaves and every section), values given the wrong type,
lists emptied, sizes made to disagree; the scene path pointed out of the bundle (``..``, an
absolute path), through a symbolic link, at a truncated or non-MJB file. Each must be one
:class:`UsageError` line from ``Bundle.load`` / ``Bundle.scene`` / ``Sim2Sim`` - never a
``KeyError``, ``IndexError`` or ``EOFError`` - and the command lines exit 2 with one line.
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from march.sim2sim.bundle_schema import SCHEMA, SchemaError, check_spec

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def good(bundle, tmp_path_factory) -> Path:
    """A private copy of the smoke bundle (the tests write into it)."""
    out = tmp_path_factory.mktemp("bundle_copy")
    for f in bundle.parent.iterdir():
        shutil.copy2(f, out / f.name)
    return out / bundle.name


@pytest.fixture(scope="module")
def spec(good) -> dict:
    return json.loads(good.with_suffix(".deploy.json").read_text())


def _load_with(good: Path, spec: dict, course: str | None = None):
    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.runner import Sim2Sim

    good.with_suffix(".deploy.json").write_text(json.dumps(spec))
    b = Bundle.load(good)
    if course is not None:
        Sim2Sim(b, course)
    return b


def _refused(good: Path, spec: dict, course: str | None = None) -> str:
    from march.sim2sim.deploy_bundle import UsageError

    try:
        _load_with(good, spec, course)
    except UsageError as err:
        line = str(err)
        assert "\n" not in line and line
        return line
    raise AssertionError("accepted")


def _paths(node, prefix=()):
    """Every key path of the JSON (dicts only; lists by their first element)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield (*prefix, k)
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list) and node and isinstance(node[0], (dict, list)):
        yield from _paths(node[0], (*prefix, 0))


def _get(node, path):
    for p in path[:-1]:
        node = node[p]
    return node


def test_the_good_bundle_passes_the_schema(spec, good):
    check_spec(spec)
    _load_with(good, spec, "hardware")


def test_every_key_is_required(spec, good):
    # every key but reset_pose_range's axes (the reset draws any subset of x y z roll pitch yaw)
    paths = [
        p
        for p in _paths(spec)
        if not isinstance(p[-1], int) and (p[:2] != ("robot", "reset_pose_range") or len(p) == 2)
    ]
    assert len(paths) > 150
    rng = np.random.default_rng(0)
    chosen = [p for p in paths if len(p) <= 2] + [
        paths[i] for i in rng.choice(len(paths), 60, replace=False)
    ]
    for path in chosen:
        broken = copy.deepcopy(spec)
        del _get(broken, path)[path[-1]]
        line = _refused(good, broken)
        assert repr(path[-1]) in line or "format" in line, (path, line)
    _load_with(good, spec)


@pytest.mark.parametrize(
    "path,value",
    [
        (("joints", 3, "kp"), "abc"),
        (("joints", 0, "motor_index"), 1.5),
        (("rates", "decimation"), "4"),
        (("rates", "physics_dt_s"), None),
        (("robot", "default_joint_pos"), [0.0] * 28),
        (("action", "scale", 2), float("nan")),
        (("courses", "hardware", "cells"), []),
        (("courses", "stones", "cells", 0), []),
        (("courses", "hardware", "scene"), 7),
        (("observation", "history_len"), 0),
        (("command", "heading_control"), "yes"),
        (("deploy", "watchdog_s"), [0.05]),
        (("checkpoint", "layout", "image_hw"), [24]),
        (("onnx", "file"), "other.onnx"),
        (("joints", 5, "motor_index"), 0),  # two joints on slot 0
        (("joints", 5, "motor_index"), 35),  # no such slot
        (("joints", 5, "name"), "right_knee_joint"),  # not the policy's order
    ],
)
def test_a_wrong_type_or_size_is_one_line(spec, good, path, value):
    broken = copy.deepcopy(spec)
    _get(broken, path)[path[-1]] = value
    _refused(good, broken)
    _load_with(good, spec)


def test_every_schema_leaf_refuses_a_string_where_a_number_belongs(spec, good):
    """Generated: each numeric leaf of the schema's top sections, set to a string."""
    count = 0
    for path in _paths(spec):
        if isinstance(path[-1], int) or path[0] == "courses":
            continue
        value = _get(spec, path)[path[-1]]
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            with pytest.raises(SchemaError):
                broken = copy.deepcopy(spec)
                _get(broken, path)[path[-1]] = "1"
                check_spec(broken)
            count += 1
    assert count > 15


def _rehash(spec: dict, course: str, data: bytes, name: str, folder: Path) -> dict:
    spec = copy.deepcopy(spec)
    (folder / name).write_bytes(data)
    spec["courses"][course]["scene"] = name
    spec["courses"][course]["sha256"] = hashlib.sha256(data).hexdigest()
    return spec


def test_scene_paths_stay_in_the_bundle_and_links_are_not_followed(spec, good, tmp_path):
    folder = good.parent
    outside = tmp_path / "outside.mjb.gz"
    scene = folder / spec["courses"]["hardware"]["scene"]
    shutil.copy2(scene, outside)
    for name in ("../../../../etc/hostname", str(outside), "sub/x.mjb.gz", "..", ""):
        broken = copy.deepcopy(spec)
        broken["courses"]["hardware"]["scene"] = name
        assert "not a file name inside the bundle" in _refused(good, broken, "hardware")
    link = folder / "link.mjb.gz"
    link.unlink(missing_ok=True)
    link.symlink_to(outside)
    broken = copy.deepcopy(spec)
    broken["courses"]["hardware"]["scene"] = link.name
    assert "symbolic link" in _refused(good, broken, "hardware")
    link.unlink()
    _load_with(good, spec, "hardware")


def test_a_truncated_or_foreign_scene_is_one_line(spec, good):
    folder = good.parent
    packed = (folder / spec["courses"]["hardware"]["scene"]).read_bytes()
    import gzip

    raw = gzip.decompress(packed)
    cases = {
        "cut.mjb.gz": packed[: len(packed) // 2],  # EOFError in gzip
        "plain.mjb.gz": b"not gzip at all",
        "cutmjb.mjb.gz": gzip.compress(raw[: len(raw) // 3]),  # MuJoCo's loader
        "text.mjb.gz": gzip.compress(b"<mujoco/>"),
        "empty.mjb.gz": b"",
    }
    for name, data in cases.items():
        broken = _rehash(spec, "hardware", data, name, folder)
        line = _refused(good, broken, "hardware")
        assert "scene" in line or "MuJoCo" in line, (name, line)


def test_a_scene_that_lacks_a_named_part_is_one_line(spec, good):
    broken = copy.deepcopy(spec)
    broken["robot"]["root_body"] = "no_such_body"
    assert "does not fit" in _refused(good, broken, "hardware")


def _cli(*words: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "march.sim2sim", *words],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_command_line_gives_one_line_for_a_broken_bundle(spec, good):
    broken = copy.deepcopy(spec)
    broken["courses"]["hardware"]["scene"] = "../../../../etc/hostname"
    good.with_suffix(".deploy.json").write_text(json.dumps(broken))
    try:
        for words in (
            (f"onnx={good}", "seconds=0.1"),
            (f"onnx={good}", "seconds=0.1", "vx=nan"),
            (f"onnx={good}", "seconds=0.1", "vy=inf"),
        ):
            res = _cli(*words)
            assert res.returncode == 2, res.stderr
            lines = res.stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
            assert "Traceback" not in res.stderr
    finally:
        good.with_suffix(".deploy.json").write_text(json.dumps(spec))
    assert "finite" in _cli(f"onnx={good}", "vx=nan").stderr


def test_export_refuses_an_existing_file_as_out_before_any_work(tmp_path):
    target = tmp_path / "a_file"
    target.write_text("keep me")
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "march.export",
            f"student_ckpt={tmp_path / 'x.pt'}",
            f"out={target}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 2 and "exists and is not a folder" in res.stderr, res.stderr
    assert target.read_text() == "keep me"
    assert len(res.stderr.strip().splitlines()) == 1


def test_schema_covers_every_section_the_export_writes(spec):
    assert set(SCHEMA) == set(spec)


@pytest.mark.parametrize(
    "field,value,words",
    [
        ("kp", -500.0, "kp = -500"),
        ("torque_limit", 1e9, "torque_limit = 1e+09"),
        ("kd", -1.0, "kd = -1"),
        ("default_pos", 3.5, "default_pos = 3.5"),
    ],
)
def test_motor_values_out_of_the_g1_ranges_are_refused_by_sim2sim_and_the_robot(
    spec, good, field, value, words
):
    """kp -500 and a torque limit of 1e9 passed both tools before (issue 47, item 3)."""
    broken = copy.deepcopy(spec)
    broken["joints"][3][field] = value  # left knee
    if field == "default_pos":
        broken["robot"]["default_joint_pos"][3] = value
    good.with_suffix(".deploy.json").write_text(json.dumps(broken))
    try:
        for cmd in (
            ["march.sim2sim", f"onnx={good}", "seconds=0.1"],
            ["march.robot", "selftest", f"bundle={good}", "seconds=0.5"],
            ["march.robot", "policy", f"bundle={good}", "interface=lo"],
        ):
            res = subprocess.run(
                [sys.executable, "-m", *cmd], cwd=ROOT, capture_output=True, text=True,
                timeout=300,
            )  # fmt: skip
            lines = res.stderr.strip().splitlines()
            assert res.returncode == 2 and len(lines) == 1, (cmd, res.stderr[-500:])
            assert words in lines[0] and "joints[3]" in lines[0], lines[0]
    finally:
        good.with_suffix(".deploy.json").write_text(json.dumps(spec))
