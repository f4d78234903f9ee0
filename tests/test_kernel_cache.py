"""numba's on-disk kernel cache follows every kernel source (ace_drake/__init__.py)."""

import ace_drake


def test_the_kernel_cache_is_renamed_when_any_kernel_source_changes(tmp_path):
    (tmp_path / "physics").mkdir()
    (tmp_path / "physics" / "contact.py").write_text("import numba\n\ndef gap(): return 1.0\n")
    (tmp_path / "physics" / "propagate.py").write_text("import numba\n\ndef flight(): return 2.0\n")
    (tmp_path / "cli.py").write_text("def main(): pass\n")
    first = ace_drake._kernel_cache_dir(tmp_path)
    assert first.is_dir() and first.parent == tmp_path / "__pycache__"
    (tmp_path / "cli.py").write_text("def main(): return 0\n")  # no kernels: the same cache
    assert ace_drake._kernel_cache_dir(tmp_path) == first
    (tmp_path / "physics" / "contact.py").write_text("import numba\n\ndef gap(): return 3.0\n")  # a callee's file
    assert ace_drake._kernel_cache_dir(tmp_path) != first


def test_the_cache_directory_reaches_numba_whichever_is_imported_first(tmp_path):
    """In a fresh interpreter without NUMBA_CACHE_DIR, numba's configuration points at the package's
    kernel cache whether numba or ace_drake is imported first; a user's NUMBA_CACHE_DIR is kept."""
    import os
    import pathlib
    import subprocess
    import sys

    expected = str(ace_drake._kernel_cache_dir(pathlib.Path(ace_drake.__file__).resolve().parent))
    environment = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    for imports in ("import numba, ace_drake", "import ace_drake, numba"):
        script = f"{imports}; print(numba.config.CACHE_DIR)"
        out = subprocess.run([sys.executable, "-c", script], env=environment, capture_output=True, text=True, check=True).stdout
        assert out.strip() == expected, imports
    script = "import numba, ace_drake; print(numba.config.CACHE_DIR)"
    out = subprocess.run([sys.executable, "-c", script], env={**environment, "NUMBA_CACHE_DIR": str(tmp_path)}, capture_output=True,
                         text=True, check=True).stdout
    assert out.strip() == str(tmp_path)
