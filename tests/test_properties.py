"""Property-based tests (issue 14): the YAML reader, the motion-file reader and the dataset reader,
fed arbitrary bytes, arbitrary YAML-like text and arbitrary values, never raise anything but their
own error, never take long on one input, and never hand on a non-finite number or a non-rigid pose."""

from __future__ import annotations

import copy
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from supervisor.dataset.format import FRAMES_FILE, METADATA_FILE, Dataset
from supervisor.errors import ConfigError, DatasetError
from supervisor.yamlschema import Ambiguous, Node, load_yaml, load_yaml_text
from test_dataset_format import _write

PROPS = settings(max_examples=100, deadline=2000, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                        HealthCheck.too_slow])

# Scalars chosen to hit YAML's corners: 1.1-vs-1.2 readings, non-finite numbers, huge numbers.
TRICKY = ["020", "010", "0755", "09", "1:00", "1:30.5", "no", "yes", "on", "off", "No", "true", "False", "~", "null",
          ".nan", ".NaN", ".inf", "-.inf", "+.inf", "1e999", "-1e999", "1e3", "1_000", "0o17", "0x1F", "0b101",
          "2001-12-14", "=", "<<", "1" * 40, "-0", "+12", ".5", "5.", "'020'", '"no"', "!!int 020", "!!float .nan",
          "!!bool yes", "!!binary aGk=", "!!set {a}", "!!python/object:os.system x", "*undefined", "&a 1"]
scalar = st.one_of(st.sampled_from(TRICKY), st.integers(-10 ** 6, 10 ** 6).map(str),
                   st.floats(allow_nan=True, allow_infinity=True).map(repr),
                   st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=12))


def _yaml_value(depth: int = 0) -> st.SearchStrategy[str]:
    if depth >= 3:
        return scalar
    inner = _yaml_value(depth + 1)
    return st.one_of(scalar,
                     st.lists(inner, max_size=4).map(lambda xs: "[" + ", ".join(xs) + "]"),
                     st.dictionaries(st.sampled_from(["a", "b", "n_t", "no", "1"]), inner, max_size=3).map(
                         lambda d: "{" + ", ".join(f"{k}: {v}" for k, v in d.items()) + "}"))


yaml_doc = st.dictionaries(st.sampled_from(["kind", "azimuth_deg", "sweep_deg", "scene", "n_t", "x", "no"]),
                           _yaml_value(), max_size=5).map(lambda d: "".join(f"{k}: {v}\n" for k, v in d.items()))
yaml_noise = st.text(st.sampled_from(list(":-[]{},&*!#|>'\"\n ?.0123456789aeflnosty~%@`\t")), max_size=80)

any_text = st.one_of(yaml_doc, yaml_noise, st.binary(max_size=200).map(lambda b: b.decode("latin-1")))

def _check_node_values(data) -> None:
    """Every typed getter either refuses a value or returns a finite, typed one."""
    if not isinstance(data, dict):
        return
    for key in list(data):
        if not isinstance(key, str):
            continue
        for getter in ("number", "integer", "boolean", "string", "optional_number"):
            node = Node(data, "f")
            try:
                v = getattr(node, getter)(key)
            except ConfigError:
                continue
            if getter in ("number", "optional_number") and v is not None:
                assert isinstance(v, float) and math.isfinite(v)
            if getter == "integer":
                assert type(v) is int
            if getter == "boolean":
                assert type(v) is bool and not isinstance(data[key], Ambiguous)
            if getter == "string":
                assert type(v) is str
        try:
            Node(data, "f").vector(key, 3)
        except ConfigError:
            pass
        else:
            assert np.all(np.isfinite(Node(data, "f").vector(key, 3)))


@PROPS
@given(st.binary(max_size=400))
def test_yaml_reader_arbitrary_bytes(tmp_path, raw):
    f = tmp_path / "c.yaml"
    f.write_bytes(raw)
    try:
        data = load_yaml(f)
    except ConfigError as e:
        assert e.file == str(f)
        return
    _check_node_values(data)


@PROPS
@given(st.one_of(yaml_doc, yaml_noise))
def test_yaml_reader_arbitrary_yaml(text):
    try:
        data = load_yaml_text(text, "f")
    except ConfigError as e:
        assert e.file == "f" and "\n" not in str(e)
        return
    _check_node_values(data)


@PROPS
@given(any_text)
def test_config_reader_arbitrary_yaml(tmp_path, text):
    from supervisor.config import load_config

    f = tmp_path / "cfg.yaml"
    f.write_text(text, encoding="utf-8")  # never a valid config: every required key is missing
    with pytest.raises(ConfigError):
        load_config(f)


@PROPS
@given(any_text)
def test_motion_reader(tmp_path, text):
    from supervisor.dryrun import load_motion

    f = tmp_path / "m.yaml"
    f.write_text(text, encoding="utf-8")
    try:
        m = load_motion(f)
    except ConfigError:
        return
    assert math.isfinite(m["azimuth"]) and 0 <= m["azimuth"] <= 2 * math.pi
    assert m["sweep"] is None or (math.isfinite(m["sweep"]) and m["sweep"] > 0)
    assert m["scene"] is None or type(m["scene"]) is str


# ---------------------------------------------------------------------------- the dataset reader

def _json_containers(children: st.SearchStrategy) -> st.SearchStrategy:
    return st.one_of(st.lists(children, max_size=5), st.dictionaries(st.text(max_size=5), children, max_size=4))


json_value = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10 ** 20, 10 ** 20), st.floats(allow_nan=True),
              st.text(max_size=10), st.sampled_from(["../x.png", "/etc/passwd", "a\x00b", "model/model_0.png"])),
    _json_containers, max_leaves=10)


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    return _write(tmp_path_factory.mktemp("prop") / "ds")


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, (*prefix, i))


def _fresh(base: Path, tmp: Path) -> Path:
    if tmp.exists():
        shutil.rmtree(tmp)
    shutil.copytree(base, tmp)
    return tmp


def _assert_sane(ds: Dataset) -> None:
    i = ds.intrinsics
    assert i.width > 0 and i.height > 0 and i.fx > 0 and i.fy > 0 and math.isfinite(i.fx + i.fy + i.cx + i.cy)
    for rec in [*ds.model_images, *ds.frames]:
        assert np.all(np.isfinite(rec.q)) and math.isfinite(rec.t) and math.isfinite(rec.s)
        for T in (rec.T_base_flange, rec.T_cam_target_true):
            if T is not None:
                assert np.all(np.isfinite(T)) and np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() < 1e-3
        assert ds.root.resolve() in ds.path_of(rec).parents


def _open_edited(base: Path, tmp_path: Path, name: str, text: str) -> None:
    """A copy of the base dataset with `name` replaced by `text`: refused, or sane if accepted."""
    root = _fresh(base, tmp_path / "ds")
    (root / name).write_text(text)
    try:
        ds = Dataset.open(root)
    except DatasetError:
        return
    _assert_sane(ds)


@PROPS
@given(data=st.data())
def test_dataset_reader_arbitrary_metadata_values(base, tmp_path, data):
    meta = json.loads((base / METADATA_FILE).read_text())
    paths = [p for p in _paths(meta) if p]
    edited = copy.deepcopy(meta)
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        target = edited
        try:
            for k in path[:-1]:
                target = target[k]
            target[path[-1]] = data.draw(json_value)
        except (KeyError, IndexError, TypeError):
            continue
    _open_edited(base, tmp_path, METADATA_FILE, json.dumps(edited))


@PROPS
@given(data=st.data())
def test_dataset_reader_arbitrary_frame_cells(base, tmp_path, data):
    lines = (base / FRAMES_FILE).read_text().splitlines()
    header = lines[0].split(",")
    row = data.draw(st.integers(1, len(lines) - 1))
    cells = lines[row].split(",")
    col = data.draw(st.integers(0, len(header) - 1))
    cells[col] = data.draw(st.one_of(st.sampled_from(["nan", "inf", "-inf", "1e999", "", "../x.png", "/etc/passwd",
                                                      "2", "-1", "0.5"]), st.text(max_size=8)))
    lines[row] = ",".join(cells)
    _open_edited(base, tmp_path, FRAMES_FILE, "\n".join(lines) + "\n")


@PROPS
@given(which=st.sampled_from([METADATA_FILE, FRAMES_FILE]), raw=st.binary(max_size=300))
def test_dataset_reader_arbitrary_bytes(base, tmp_path, which, raw):
    root = _fresh(base, tmp_path / "ds")
    (root / which).write_bytes(raw)
    with pytest.raises(DatasetError):
        Dataset.open(root)
