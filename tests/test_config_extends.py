"""`extends:` — a configuration laid over another (the embedded default or a file), as a cell's own config is."""

from __future__ import annotations

import math

import pytest
import yaml

from supervisor.config import MAX_EXTENDS_DEPTH, load_config
from supervisor.errors import ConfigError
from supervisor.paths import DEFAULT_CONFIG


def write(path, doc) -> str:
    path.write_text(yaml.safe_dump(doc, sort_keys=False) if not isinstance(doc, str) else doc)
    return path


def test_keys_merge_into_the_default_stage_by_stage(tmp_path):
    default = load_config()
    cfg = load_config(write(tmp_path / "cell.yaml", {
        "extends": "default",
        "robot": {"q_start_deg": [0, -40, 0, -130, 0, 90, 45]},   # a list replaces the default's
        "stages": {"explore": {"n_t": 9, "limits": {"velocity_deg_s": 5}}},
        "default_stage": "cut",
    }))
    assert cfg.robot.q_start[1] == pytest.approx(math.radians(-40)) and cfg.robot.driver == default.robot.driver
    ex, ex0 = cfg.stages["explore"], default.stages["explore"]
    assert ex.n_t == 9 and ex0.n_t != 9
    assert ex.limits.velocity == pytest.approx(math.radians(5))
    assert ex.limits.acceleration == ex0.limits.acceleration  # the rest of `limits` is the default's
    assert (ex.variant, ex.step, ex.min_inlier_ratio) == (ex0.variant, ex0.step, ex0.min_inlier_ratio)
    assert cfg.stages["cut"] == default.stages["cut"] and list(cfg.stages) == list(default.stages)
    assert cfg.default_stage == "cut" and cfg.file == str(tmp_path / "cell.yaml")


def test_a_chain_of_files_relative_to_each_other(tmp_path):
    (tmp_path / "site").mkdir()
    write(tmp_path / "site" / "base.yaml", {"extends": "default", "camera": {"frame_rate_hz": 15}})
    cfg = load_config(write(tmp_path / "cell.yaml", {"extends": "site/base.yaml", "camera": {"fx": 1500}}))
    assert cfg.camera.frame_period_s == pytest.approx(1 / 15) and cfg.camera.intrinsics.fx == 1500


def test_null_replaces_a_section(tmp_path):
    base = write(tmp_path / "base.yaml", DEFAULT_CONFIG.read_text() + "can:\n  interface: virtual\n"
                 "  channel: cell\n")
    assert load_config(base).can is not None
    assert load_config(write(tmp_path / "off.yaml", {"extends": "base.yaml", "can": None})).can is None


def test_the_hash_covers_the_base(tmp_path):
    base = write(tmp_path / "base.yaml", {"extends": "default", "camera": {"frame_rate_hz": 15}})
    top = write(tmp_path / "top.yaml", {"extends": "base.yaml"})
    first = load_config(top).sha256
    write(base, {"extends": "default", "camera": {"frame_rate_hz": 20}})
    assert load_config(top).sha256 != first and top.read_text() == "extends: base.yaml\n"
    assert first != load_config(base).sha256 != load_config().sha256


@pytest.mark.parametrize("value, problem", [
    (3, "expected 'default' (the embedded configuration) or a file name, got 3"),
    ("", "or a file name, got ''"),
    ("nowhere.yaml", "nowhere.yaml' does not exist (a relative name is taken from this file's folder)"),
    (".", "is not a regular file"),
])
def test_a_bad_extends_names_the_file_and_key(tmp_path, value, problem):
    f = write(tmp_path / "cell.yaml", {"extends": value})
    with pytest.raises(ConfigError) as info:
        load_config(f)
    assert (info.value.file, info.value.key) == (str(f), "extends") and problem in info.value.problem


def test_a_cycle_is_refused_by_name(tmp_path):
    write(tmp_path / "a.yaml", {"extends": "b.yaml"})
    write(tmp_path / "b.yaml", {"extends": "a.yaml"})
    with pytest.raises(ConfigError, match=r"extends: the files extend each other in a cycle: .*a\.yaml -> "
                                          r".*b\.yaml -> .*a\.yaml"):
        load_config(tmp_path / "a.yaml")
    write(tmp_path / "self.yaml", {"extends": "self.yaml"})
    with pytest.raises(ConfigError, match="cycle"):
        load_config(tmp_path / "self.yaml")


def test_a_long_chain_is_refused(tmp_path):
    write(tmp_path / "c0.yaml", {"extends": "default"})
    for i in range(1, MAX_EXTENDS_DEPTH + 1):
        write(tmp_path / f"c{i}.yaml", {"extends": f"c{i - 1}.yaml"})
    assert load_config(tmp_path / f"c{MAX_EXTENDS_DEPTH - 1}.yaml").stages
    with pytest.raises(ConfigError, match=f"more than {MAX_EXTENDS_DEPTH} files extend one another"):
        load_config(tmp_path / f"c{MAX_EXTENDS_DEPTH}.yaml")


def test_an_error_in_the_base_names_the_base(tmp_path):
    base = write(tmp_path / "base.yaml", {"extends": "default", "stages": {"explore": {"n_t": -3}}})
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path / "top.yaml", {"extends": "base.yaml", "stages": {"explore": {"n_t": 9}}}))
    assert (info.value.file, info.value.key) == (str(base), "stages.explore.n_t")


def test_an_error_deep_in_the_chain_names_its_file_and_the_chain_is_recorded(tmp_path):
    root = write(tmp_path / "root.yaml", {"extends": "default", "camera": {"frame_rate_hz": -1}})
    site = write(tmp_path / "site.yaml", {"extends": "root.yaml", "stages": {"cut": {"n_t": 12}}})
    cell = write(tmp_path / "cell.yaml", {"extends": "site.yaml", "stages": {"cut": {"n_t": 13}}})
    with pytest.raises(ConfigError) as info:  # the site file does not fix it: the root is wrong on its own
        load_config(cell)
    assert info.value.file == str(root) and info.value.key.startswith("camera.frame_rate")
    write(root, {"extends": "default", "camera": {"frame_rate_hz": 15}})
    cfg = load_config(cell)
    assert cfg.files == (cell, site, root, DEFAULT_CONFIG) and cfg.stages["cut"].n_t == 13
    assert load_config().files == (DEFAULT_CONFIG,)


def test_an_error_in_the_overlay_names_the_overlay(tmp_path):
    top = write(tmp_path / "top.yaml", {"extends": "default", "stages": {"explore": {"n_tt": 9}}})
    with pytest.raises(ConfigError) as info:
        load_config(top)
    assert info.value.file == str(top) and info.value.key == "stages.explore.n_tt"
    top = write(tmp_path / "new.yaml", {"extends": "default", "stages": {"mine": {"n_t": 9}}})
    with pytest.raises(ConfigError) as info:  # a new stage is a whole stage: nothing to merge it into
        load_config(top)
    assert info.value.file == str(top) and info.value.key.startswith("stages.mine")


def test_config_check_prints_the_chain_and_the_stages(tmp_path, capsys):
    from supervisor.cli import main

    site = write(tmp_path / "site.yaml", {"extends": "default", "stages": {"cut": {"n_t": 12}}})
    cell = write(tmp_path / "cell.yaml", {"extends": "site.yaml", "robot": {"driver": "franka", "host": "10.0.0.2"}})
    assert main(["config", "check", str(cell)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"ok: {cell}\n  extends: {site} -> default (")
    assert f"sha256: {load_config(cell).sha256}" in out and "robot: franka (panda) at 10.0.0.2, 250 Hz" in out
    assert "    cut                  next_step local_lcb, n_t 12, stop_and_go 1 deg steps" in out
    assert "tuned for 2 mm / 3 deg" in out
    write(site, {"extends": "default", "stages": {"cut": {"n_t": 2}}})
    assert main(["config", "check", str(cell)]) == 2
    assert capsys.readouterr().err.strip() == f"error: {site}: stages.cut.n_t: must be >= 4, got 2"


def test_config_show_is_the_merged_document_and_loads_the_same(tmp_path, capsys):
    from supervisor.cli import main

    cell = write(tmp_path / "cell.yaml", {"extends": "default", "stages": {"explore": {"n_t": 9}}})
    assert main(["config", "show", str(cell)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"# effective configuration of {cell}\n# extends default (")
    assert "extends" not in yaml.safe_load(text)
    flat = load_config(write(tmp_path / "flat.yaml", text))
    assert flat.stages == load_config(cell).stages and flat.stages["explore"].n_t == 9
    assert main(["--config", str(cell), "config", "show"]) == 0 and capsys.readouterr().out == text
