import math

import numpy as np
import pytest

from supervisor.errors import ConfigError
from supervisor.yamlschema import Node, load_yaml, load_yaml_text


def test_duplicate_key_rejected_with_file(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("a: 1\nb:\n  x: 1\n  x: 2\n")
    with pytest.raises(ConfigError) as ei:
        load_yaml(f)
    assert str(f) in str(ei.value) and "duplicate key 'x'" in str(ei.value)


def test_missing_file_is_config_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read file"):
        load_yaml(tmp_path / "nope.yaml")


@pytest.mark.parametrize(
    "text, problem",
    [
        ("stages:\n  drill:\n    n_t: .nan\n", "must be a finite number"),
        ("stages:\n  drill:\n    n_t: 2\n", "must be >= 4"),
        ("stages:\n  drill:\n    n_t: no\n", "'no' is the boolean false in YAML 1.1 but a string in YAML 1.2"),
        ("stages:\n  drill:\n    n_t: false\n", "expected a number, got boolean false"),
        ("stages:\n  drill:\n    n_t: '15'\n", "expected a number"),
    ],
)
def test_number_validation_names_dotted_key(text, problem):
    root = Node(load_yaml_text(text, "f.yaml"), "f.yaml")
    with pytest.raises(ConfigError) as ei:
        root.child("stages").child("drill").number("n_t", min=4)
    assert "f.yaml: stages.drill.n_t:" in str(ei.value)
    assert problem in str(ei.value)


def test_unknown_key_rejected():
    n = Node({"a": 1, "typo": 2}, "f.yaml")
    n.integer("a")
    with pytest.raises(ConfigError, match="typo: unknown key"):
        n.done()


def test_octal_looking_int_and_vector():
    # YAML 1.1 read 0755 as 493, YAML 1.2 as 755: a threshold must mean what it says, so it is refused;
    # only the explicit 0o755 is octal.
    n = Node(load_yaml_text("mode: 0755\nm: 0o755\nv: [1, 2.5, 3]\n"), "f")
    with pytest.raises(ConfigError, match=r"f: mode: expected an integer: '0755' is ambiguous: YAML 1.1 reads it as the octal 493"):
        n.integer("mode")
    assert n.integer("m") == 493
    v = n.vector("v", 3)
    assert np.allclose(v, [1, 2.5, 3]) and not v.flags.writeable
    with pytest.raises(ConfigError, match=r"v: expected a list of 2 numbers"):
        Node({"v": [1, 2, 3]}, "f").vector("v", 2)
    with pytest.raises(ConfigError, match=r"v\[1\]: must be a finite number"):
        Node({"v": [1, math.inf]}, "f").vector("v", 2)


def test_choices_and_types():
    n = Node({"m": "flan", "b": 1}, "f")
    with pytest.raises(ConfigError, match="expected one of bf, flann"):
        n.string("m", choices=["flann", "bf"])
    with pytest.raises(ConfigError, match="expected true or false"):
        n.boolean("b")
    with pytest.raises(ConfigError, match="expected a mapping"):
        Node([1, 2], "f")
