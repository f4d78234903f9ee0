"""The layer contract (docs/architecture.md): import-linter's check, as the tests run it."""

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_no_module_imports_from_a_layer_above_it():
    lint_imports = pathlib.Path(sys.executable).with_name("lint-imports")
    result = subprocess.run([str(lint_imports), "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "1 kept, 0 broken" in result.stdout


def test_the_contract_catches_an_upward_import(tmp_path):
    """The same contract on a copy of the package with one upward import (physics -> control)
    is broken: the check can fail."""
    package = tmp_path / "ace_drake"
    subprocess.run(["cp", "-r", str(ROOT / "ace_drake"), str(package)], check=True)
    (package / "physics" / "upward.py").write_text("from ace_drake.control import stack\n")
    (tmp_path / "pyproject.toml").write_text((ROOT / "pyproject.toml").read_text())
    lint_imports = pathlib.Path(sys.executable).with_name("lint-imports")
    result = subprocess.run([str(lint_imports)], cwd=tmp_path, capture_output=True, text=True, env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert result.returncode != 0
    assert "ace_drake.physics.upward -> ace_drake.control.stack" in result.stdout
