"""Hostile and careless YAML (issue 14): every case ends in one ConfigError naming the file, quickly."""

from __future__ import annotations

import os
import threading
import time

import pytest

from supervisor.config import load_config
from supervisor.errors import ConfigError
from supervisor.yamlschema import MAX_BYTES, Node, _type_name, load_yaml, load_yaml_text


def _bomb(levels: int, width: int = 9) -> str:
    lines = [f"l0: &l0 [{', '.join(['lol'] * width)}]"]
    for i in range(1, levels):
        lines.append(f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * width)}]")
    return "\n".join(lines) + f"\nrobot: *l{levels - 1}\n"


def test_deep_nesting_is_refused_not_a_recursion_error(tmp_path):
    f = tmp_path / "deep.yaml"
    f.write_text("a: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ConfigError, match=r"deep.yaml: invalid YAML at line 1, column \d+: nested deeper than"):
        load_config(f)
    block = "".join(f"{' ' * (2 * i)}k{i}:\n" for i in range(3000))
    with pytest.raises(ConfigError, match="nested deeper than"):
        load_yaml_text(block, "f")


def test_alias_bomb_is_refused_quickly(tmp_path):
    f = tmp_path / "bomb.yaml"
    f.write_text(_bomb(10))
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match="bomb.yaml: invalid YAML at line .*aliases expand to more than"):
        load_config(f)
    assert time.monotonic() - t0 < 5.0


def test_small_alias_bomb_under_a_checked_key_gives_a_short_message(tmp_path):
    # 8^5 = 32768 leaves (twice): under the expansion budget, so the schema sees it; its message must stay short
    f = tmp_path / "c.yaml"
    f.write_text(_bomb(5, width=8))
    with pytest.raises(ConfigError) as ei:
        load_config(f)
    assert len(str(ei.value)) < 300
    assert "robot" in str(ei.value)


def test_recursive_alias_is_refused():
    with pytest.raises(ConfigError, match="refers to the node that contains it"):
        load_yaml_text("a: &a [1, *a]\n", "f")


def test_type_name_never_reprs_a_structure():
    big = [list(range(1000))] * 1000
    assert len(_type_name(big)) < 40
    assert len(_type_name({str(i): i for i in range(10_000)})) < 40
    assert len(_type_name("x" * 100_000)) < 80


@pytest.mark.parametrize("special", ["/dev/zero", "/dev/null", "dir", "fifo"])
def test_non_regular_files_are_refused_before_reading(tmp_path, special):
    if special == "dir":
        path = tmp_path
    elif special == "fifo":
        path = tmp_path / "cfg.fifo"
        os.mkfifo(path)
    else:
        path = special
    result: list[BaseException | None] = []

    def load() -> None:
        try:
            load_config(path)
            result.append(None)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            result.append(exc)

    t = threading.Thread(target=load, daemon=True)
    t.start()
    t.join(10.0)
    assert not t.is_alive(), "load_config blocked on a special file"
    assert isinstance(result[0], ConfigError)
    assert f"{path}: cannot read configuration: " in str(result[0]) and "not a regular file" in str(result[0])


def test_oversized_file_is_refused(tmp_path):
    f = tmp_path / "big.yaml"
    f.write_text("a: " + "x" * (MAX_BYTES + 10) + "\n")
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=r"big.yaml: cannot read configuration: \d+ bytes, more than the"):
        load_config(f)
    with pytest.raises(ConfigError, match="more than the"):
        load_yaml(f)
    assert time.monotonic() - t0 < 2.0


@pytest.mark.parametrize("text, reason", [
    ("n_t: 020", "'020' is ambiguous: YAML 1.1 reads it as the octal 16, YAML 1.2 as 20"),
    ("n_t: 010", "'010' is ambiguous: YAML 1.1 reads it as the octal 8"),
    ("n_t: 1:00", "'1:00' is the integer 60 in YAML 1.1 but a string in YAML 1.2"),
    ("n_t: 1_000", "'1_000' is the integer 1000 in YAML 1.1"),
    ("n_t: 0755", "'0755' is ambiguous: YAML 1.1 reads it as the octal 493"),
])
def test_yaml11_numbers_are_refused_with_key_and_reason(text, reason):
    n = Node(load_yaml_text(text, "f.yaml"), "f.yaml")
    with pytest.raises(ConfigError) as ei:
        n.integer("n_t")
    assert str(ei.value).startswith("f.yaml: n_t: expected an integer: ") and reason in str(ei.value)
    with pytest.raises(ConfigError, match="n_t: expected a number: "):
        Node(load_yaml_text(text, "f.yaml"), "f.yaml").number("n_t")


@pytest.mark.parametrize("word", ["no", "yes", "on", "off", "No", "OFF"])
def test_yaml11_booleans_are_refused_as_booleans_kept_as_strings(word):
    n = Node(load_yaml_text(f"refine_continuous: {word}\nroi: {word}\n", "f.yaml"), "f.yaml")
    with pytest.raises(ConfigError, match=rf"refine_continuous: expected true or false: '{word}' is the boolean"):
        n.boolean("refine_continuous")
    assert n.string("roi") == word and type(n.string("roi")) is str


def test_yaml12_core_scalars():
    d = load_yaml_text("a: 0o17\nb: 0x1F\nc: 1e3\nd: true\ne: ~\nf: -.inf\ng: 20\nh: '020'\n", "f")
    assert d == {"a": 15, "b": 31, "c": 1000.0, "d": True, "e": None, "f": float("-inf"), "g": 20, "h": "020"}
    with pytest.raises(ConfigError, match="'yes' is not a YAML 1.2 boolean"):
        load_yaml_text("a: !!bool yes\n", "f")


def test_yaml11_config_values_are_refused(tmp_path):
    from supervisor.config import DEFAULT_CONFIG

    text = DEFAULT_CONFIG.read_text()
    assert "frames_per_step: 5" in text
    f = tmp_path / "c.yaml"
    f.write_text(text.replace("frames_per_step: 5", "frames_per_step: 010", 1))
    with pytest.raises(ConfigError, match=r"c.yaml: stages\.\w+\.frames_per_step: expected an integer: '010'"):
        load_config(f)


def test_unhashable_key_is_a_config_error():
    with pytest.raises(ConfigError, match="a mapping key must be a scalar"):
        load_yaml_text("? [1, 2]\n: 3\n", "f")
    with pytest.raises(ConfigError, match="a mapping key must be a scalar"):
        load_yaml_text("{? {a: 1} : 3}\n", "f")


def test_scene_that_is_not_yaml_is_not_echoed():
    from sim.scene import load_scene

    with pytest.raises(ConfigError) as ei:
        load_scene("/etc/passwd")
    msg = str(ei.value)
    assert msg.startswith("/etc/passwd: ") and "expected a mapping" in msg
    assert "root" not in msg and "/bin/" not in msg


def test_syntax_error_does_not_quote_the_file(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("secret_token_value: [unclosed\n  other: x\n")
    with pytest.raises(ConfigError) as ei:
        load_yaml(f)
    assert "invalid YAML at line" in str(ei.value) and "secret_token_value" not in str(ei.value)
