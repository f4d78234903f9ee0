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
