"""The YAML loader: configs composed over a base file (``base:``), and its errors."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from ace_drake.config import ConfigError, load_config, load_yaml, merge


@dataclasses.dataclass(frozen=True)
class Inner:
    a: float = 1.0
    b: tuple[int, ...] = (1, 2)


@dataclasses.dataclass(frozen=True)
class Outer:
    name: str = "x"
    inner: Inner = dataclasses.field(default_factory=Inner)


def _write(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data))
    return path


def test_merge_is_deep_for_mappings_and_replaces_everything_else():
    base = {"a": 1, "m": {"x": 1, "y": [1, 2], "n": {"p": 1}}, "l": [1]}
    assert merge(base, {"m": {"y": [3], "n": {"q": 2}}, "l": [], "b": 2}) == {
        "a": 1, "m": {"x": 1, "y": [3], "n": {"p": 1, "q": 2}}, "l": [], "b": 2}
    assert base == {"a": 1, "m": {"x": 1, "y": [1, 2], "n": {"p": 1}}, "l": [1]}  # unchanged
    assert merge({"m": {"x": 1}}, {"m": None}) == {"m": None}


def test_a_config_is_composed_over_its_base_relative_to_its_own_file(tmp_path):
    _write(tmp_path / "shared" / "root.yaml", {"name": "root", "inner": {"a": 2.0, "b": [5]}})
    _write(tmp_path / "shared" / "middle.yaml", {"base": "root.yaml", "inner": {"a": 3.0}})
    path = _write(tmp_path / "configs" / "leaf.yaml", {"base": "../shared/middle.yaml", "name": "leaf"})
    assert load_yaml(path) == {"name": "leaf", "inner": {"a": 3.0, "b": [5]}}
    assert load_config(Outer, path) == Outer("leaf", Inner(3.0, (5,)))


def test_composition_errors_name_the_file_and_the_field(tmp_path):
    _write(tmp_path / "a.yaml", {"base": "b.yaml"})
    _write(tmp_path / "b.yaml", {"base": "a.yaml"})
    with pytest.raises(ConfigError, match="a cycle of base: files"):
        load_yaml(tmp_path / "a.yaml")
    _write(tmp_path / "self.yaml", {"base": "self.yaml"})
    with pytest.raises(ConfigError, match="cycle"):
        load_yaml(tmp_path / "self.yaml")
    _write(tmp_path / "missing.yaml", {"base": "nowhere.yaml"})
    with pytest.raises(ConfigError, match=r"not found: .*nowhere.yaml \(the base of .*missing.yaml\)"):
        load_yaml(tmp_path / "missing.yaml")
    _write(tmp_path / "number.yaml", {"base": 3})
    with pytest.raises(ConfigError, match="number.yaml: base: expected a YAML file's name"):
        load_yaml(tmp_path / "number.yaml")
    _write(tmp_path / "list.yaml", [1, 2])
    _write(tmp_path / "over_list.yaml", {"base": "list.yaml"})
    with pytest.raises(ConfigError, match="list.yaml: expected a mapping"):
        load_yaml(tmp_path / "over_list.yaml")
    # A field unknown in the base or in the including file is named with its dotted path.
    _write(tmp_path / "typo_base.yaml", {"inner": {"c": 1}})
    _write(tmp_path / "typo.yaml", {"base": "typo_base.yaml", "name": "y"})
    with pytest.raises(ConfigError, match=r"typo.yaml: inner: unknown field\(s\) \['c'\]"):
        load_config(Outer, tmp_path / "typo.yaml")
    (tmp_path / "bad.yaml").write_text("a: [")
    _write(tmp_path / "over_bad.yaml", {"base": "bad.yaml"})
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML"):
        load_yaml(tmp_path / "over_bad.yaml")
