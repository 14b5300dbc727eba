"""The accuracy-versus-time study runs at a tiny size and reports the presets and the default."""

import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))


def test_study_runs_tiny_and_reports_presets(rt, tmp_path):
    import accuracy_vs_time as study
    from cm2cl.solver.params import PRESETS

    rows = study.main(["--tiny", "--out", str(tmp_path)])
    table = list(csv.DictReader(open(tmp_path / "accuracy_vs_time.csv")))
    assert len(table) == len(rows) == len(study.configs(True))
    configs = [r["config"] for r in table]
    for k in PRESETS:
        assert any(c.startswith(f"preset {k}") for c in configs), k
    assert "preset balanced (default)" in configs
    for r in table:   # every row has its cost and its accuracy
        assert float(r["seconds"]) > 0 and int(r["iterations"]) >= 1 and float(r["device_mib"]) > 0
        assert 0 <= float(r["recall"]) <= 1 and float(r["objective_gap"]) > -1e-3
    # more iterations never end farther from the long run's objective (same problem, same weights)
    gap = {r["config"]: float(r["objective_gap"]) for r in table}
    for r in table:   # iterations to 1% of the long run: reached where the row ends within 1%, never after its end
        if float(r["objective_gap"]) <= 0.01:
            assert r["it_to_1%"] and 1 <= int(r["it_to_1%"]) <= int(r["iterations"]) and float(r["s_to_1%"]) > 0
        else:
            assert not r["it_to_1%"]
    assert gap["30 iterations"] < gap["10 iterations"]
    assert any(r["pareto"] == "True" for r in table)
    md = (tmp_path / "accuracy_vs_time.md").read_text()
    assert "## Presets" in md and "**balanced**" in md and "Pareto" in md
    png = tmp_path / "img" / "accuracy_vs_time_beads.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10000
