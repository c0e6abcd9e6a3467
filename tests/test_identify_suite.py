"""benchmarks/identify_suite.py: rows of pairs run in parallel merge into one table."""

from __future__ import annotations

import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "identify_suite.py"


def _suite():
    spec = importlib.util.spec_from_file_location("identify_suite", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_parallel_parts_replace_their_scenes_rows_and_keep_the_others():
    suite = _suite()
    earlier = [
        {"scene": "scene-00-elastic-plasticine", "pair": "E-P", "code": "old"},
        {"scene": "scene-04-plasticine-sand", "pair": "P-S", "code": "old"},
        {"scene": "scene-09-sand-sand", "code": "format before pairs"},  # dropped: old format
    ]
    parts = [
        [{"scene": "scene-04-plasticine-sand", "pair": "P-S", "code": "new"}],
        [{"scene": "scene-02-elastic-sand", "pair": "E-S", "code": "new"}],
    ]
    rows = suite.merge_parts(earlier, parts)
    assert [r["scene"] for r in rows] == [
        "scene-00-elastic-plasticine",
        "scene-02-elastic-sand",
        "scene-04-plasticine-sand",
    ]
    assert [r["code"] for r in rows] == ["old", "new", "new"]


def test_a_pair_keeps_its_scene_seed_whichever_pairs_are_selected():
    """Parallel parts run one pair each; the pair's scene must be the one the serial suite
    would generate, so its index (and seed) comes from the paper's order, not the selection."""
    suite = _suite()
    assert suite.select_pairs(pairs="P-S", scenes=None) == [(4, "P-S")]
    assert suite.select_pairs(pairs="S-S,E-P", scenes=None) == [(9, "S-S"), (0, "E-P")]
