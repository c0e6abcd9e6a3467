"""mosiv_framework.testing.scripts.load_script: a benchmark script loaded with its siblings
importable while it loads, and the folder taken off sys.path again unless asked to stay."""

from __future__ import annotations

import sys

import pytest

from mosiv_framework.testing.scripts import load_script


def _scripts(tmp_path):
    (tmp_path / "sibling_for_load_test.py").write_text("VALUE = 41\n")
    (tmp_path / "script_for_load_test.py").write_text(
        "from sibling_for_load_test import VALUE\n\nANSWER = VALUE + 1\n"
    )
    return tmp_path / "script_for_load_test.py"


def test_a_script_sees_its_siblings_and_the_path_is_restored(tmp_path):
    script = _scripts(tmp_path)
    before = list(sys.path)
    module = load_script(script)
    assert module.ANSWER == 42 and module.__name__ == "script_for_load_test"
    assert sys.path == before and "script_for_load_test" not in sys.modules
    sys.modules.pop("sibling_for_load_test", None)


def test_register_and_keep_path(tmp_path):
    script = _scripts(tmp_path)
    try:
        module = load_script(script, register=True, keep_path=True)
        assert sys.modules["script_for_load_test"] is module
        assert sys.path[0] == str(tmp_path)
    finally:
        sys.modules.pop("script_for_load_test", None)
        sys.modules.pop("sibling_for_load_test", None)
        sys.path.remove(str(tmp_path))


def test_a_file_that_is_not_python_is_refused_by_name(tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("not python")
    with pytest.raises(ImportError, match="notes.txt: not a Python script"):
        load_script(notes)
