"""benchmarks/lift_gap.py: its lifter variants, its table, and the RESULTS.md table of the
paper-size round trip's lift study against the committed rows."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "benchmarks" / "data" / "capture_roundtrip_paper"


def _lift_gap():
    return load_script(ROOT / "benchmarks" / "lift_gap.py", register=True)


def test_variants_are_lifter_options_read_as_json():
    parse = _lift_gap().parse_variant
    assert parse("") == {}
    assert parse("mask_dilation_px=0, renderer=gauss-torch") == {
        "mask_dilation_px": 0,
        "renderer": "gauss-torch",
    }
    assert parse("samples_per_cell=16.5,widen_radius=null") == {
        "samples_per_cell": 16.5,
        "widen_radius": None,
    }
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        parse("mask_dilation_px")


def _rows(name: str) -> dict:
    rows = json.loads((DATA / name).read_text())["rows"]
    return {(r["run"], r["variant"]): r for r in rows}


def test_the_results_table_is_the_one_its_rows_hold():
    """Every observed / future pair and volume ratio of RESULTS' lift table is in the data, at
    the cells the table names."""
    text = (ROOT / "docs" / "RESULTS.md").read_text()
    section = text[text.index("## A recording through a rig and back") :]
    table = section[section.index("| run | cells | truth from") :]
    lines = table.split("\n\n")[0].splitlines()[2:]
    runs = {
        "direct": "crt/run_direct",
        "direct, reseeded": "crt/run_direct_reseeded",
        "keep import": "crt/run_imported",
        "drop import": "crt_drop/run_imported",
    }
    data = {64: _rows("lift_gap_grid64.json"), 86: _rows("lift_gap_cell_size.json")}
    assert len(lines) == 6
    for line in lines:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        name, grid = runs[cells[0]], int(cells[1].split("grid ")[1].rstrip(")"))
        rows = data[86 if grid == 86 else 64]
        for cell, variant in zip(
            cells[2:],
            ("scene's own points (gt-points lifter)", "the run's lifter", "mask_dilation_px=0"),
        ):
            row = rows[(name, variant)]
            assert row["grid"] == grid
            assert cell.startswith(f"{row['observed_cd']:,.0f} / {row['future_cd']:,.0f}"), cell
            if "x, " in cell:  # volume ratios, the elastic body's first
                by_material = {o["material"]: o["volume_ratio"] for o in row["objects"].values()}
                shown = cell[cell.index("(") + 1 : cell.index(")")].split(", ")
                ratios = [by_material["elastic"], by_material["plasticine"]]
                assert shown == [f"{r:.2f}x" for r in ratios], cell
