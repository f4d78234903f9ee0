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


def private_imports(package: pathlib.Path) -> list[str]:
    """Every ``from ace_drake.x import _name`` in the modules under ``package``: file, module, name."""
    import ast

    found = []
    for path in sorted(package.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("ace_drake"):
                found += [f"{path}: {node.module}.{alias.name}" for alias in node.names if alias.name.startswith("_") and alias.name != "__version__"]
    return found


def test_no_module_imports_another_modules_private_names():
    """What a module shares it names without an underscore: a private name used elsewhere is
    made public where it is defined."""
    assert private_imports(pathlib.Path(__file__).resolve().parents[1] / "ace_drake") == []


def test_the_private_import_check_catches_one(tmp_path):
    (tmp_path / "m.py").write_text("from ace_drake.physics.flight import _hidden\n")
    assert private_imports(tmp_path) == [f"{tmp_path / 'm.py'}: ace_drake.physics.flight._hidden"]

