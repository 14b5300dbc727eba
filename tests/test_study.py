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


def test_warm_start_study_coarse_problem_is_exact_for_block_constant_volumes():
    """tools/warm_start_study.py's coarse-to-fine start: for a volume constant on 2 x 2 blocks, the 2 x 2 sums
    of its image equal the coarse PSF's image of the block sums (even and odd PSF grids), and upsampling
    gives back the block-constant volume."""
    import numpy as np

    import warm_start_study as ws
    from cm2cl.analysis.quality import object_image

    rng = np.random.default_rng(2)
    for M in ((32, 40), (34, 42)):
        psf = np.zeros((2,) + M)
        psf[:, M[0] // 2 - 6:M[0] // 2 + 6, M[1] // 2 - 5:M[1] // 2 + 7] = rng.random((2, 12, 12))
        xc = np.zeros((2, M[0] // 2, M[1] // 2))
        xc[:, 5:11, 6:13] = rng.random((2, 6, 7))
        x = ws.upsample(xc, (2,) + M)
        np.testing.assert_allclose(ws.bin_sensor(x), xc, rtol=1e-14)
        a, b = ws.bin_sensor(object_image(psf, x)), object_image(ws.coarse_psf(psf), xc)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(a).max())
        # the plain 2 x 2 sum of the taps (half a pixel off, no triangle) is not that operator: the check sees it
        plain = object_image(ws.bin_sensor(psf), xc)
        assert np.abs(plain - a).max() > 0.05 * np.abs(a).max()


def test_bench_fullframe_cli_mode_runs_tiny(rt, tmp_path):
    """tools/bench_fullframe.py --cli (the full frame through `cm2cl reconstruct` from files) at a tiny size:
    it measures the command's own iterations, time and memory, and keeps the library section of the file."""
    import subprocess

    out = tmp_path / "fullframe.md"
    out.write_text("# The full-resolution frame\n\nthe library run's table\n")
    tool = Path(__file__).resolve().parents[1] / "tools" / "bench_fullframe.py"
    r = subprocess.run([sys.executable, str(tool), "--cli", "--planes", "3", "--bin", "8", "--iters", "3", "--beads",
                        "10", "--out", str(out), "--scratch", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert text.startswith("# The full-resolution frame\n\nthe library run's table\n\n## The command line")
    assert "| wall time, start to exit | " in text and " s for 3 iterations |" in text
    rss = float(text.split("| peak RSS of the command (wait4 ru_maxrss) | ")[1].split(" GiB")[0])
    assert 0.05 < rss < 4.0
    assert list(tmp_path.iterdir()) == [out]    # the inputs and the volume went with their scratch folder


def test_fit_optics_blur_section_says_which_paper_measurements_a_blur_meets():
    """The blur scan's verdict follows its numbers: a blur within 15% of the paper's PCC widths but without
    its MTF's axial bandwidth is reported as such; one that meets both is reported as meeting both; bad
    --blur items are refused with the item named."""
    import pytest

    import fit_optics as F

    def r(sigma, f, w, support, bz):
        return {"sigma": sigma, "fraction": f, "3x3": w[0], "2x3": w[1], "2x2": w[2], "support": support, "bz": bz}

    sharp = r(0, 1.0, (62, 65, 70), 0.0946, 0.0197)
    wide = r(1.0, 1.0, (139, 162, 222), 0.0618, 0.0)
    text = "\n".join(F.blur_section([sharp, wide], 0.61, 10.0))
    assert "1 of the blurs bring all three PCC widths within 15%" in text and "0.0000 / um" in text
    assert "| **139** | **162** | **222** |" in text and "| 62 | 65 | 70 |" in text
    both = r(1.2, 0.9, (150, 180, 200), 0.1, 0.014)
    assert "1 of the blurs meet the paper's PCC widths and its MTF together" in "\n".join(F.blur_section([both], 0.61, 10.0))
    assert "None of the blurs" in "\n".join(F.blur_section([sharp], 0.61, 10.0))
    assert F._parse_blurs("0, 1.5:0.84") == [(0.0, 1.0), (1.5, 0.84)]
    for bad in ("x", "1:2", "-1", "nan", "1:nan"):
        with pytest.raises(ValueError, match="--blur"):
            F._parse_blurs(bad)


def test_heldout_psf_family_is_what_its_docstring_says():
    """tools/heldout_psf.py's PSF: every plane holds unit light (equal gains), the sharpest plane is the focus
    (plane 6), the spots grow with defocus on both sides, and the outer spots move apart with depth."""
    import numpy as np

    import heldout_psf as H

    psf = H.hex_psf(12, (80, 96))
    np.testing.assert_allclose(psf.sum(axis=(1, 2)), 1.0, rtol=1e-6)
    sharp = (psf ** 2).sum(axis=(1, 2))
    assert int(np.argmax(sharp)) == 6 and np.all(np.diff(sharp[6:]) < 0) and np.all(np.diff(sharp[:7]) > 0)
    # the lenslets right of the axis: their centroid moves outward with depth
    right = psf[:, :, 48 + 12:]
    xs = np.arange(right.shape[2])
    cx = [(p.sum(axis=0) * xs).sum() / p.sum() for p in right]
    assert np.all(np.diff(cx) > 0)
    # gains scale the lenslets' light, a blur keeps each plane's light
    g = H.hex_psf(3, (80, 96), gains=[0.5] * 7, blur=0.7)
    np.testing.assert_allclose(g.sum(axis=(1, 2)), 0.5, rtol=1e-3)


def test_heldout_spread_table_tells_spread_light_from_lost_light():
    """heldout_psf's spread table on a volume whose answer is known: the true beads, with those in planes 14-17
    spread evenly over 5 planes (their peak falls to a fifth, below the detector's threshold). They are missed,
    keep their flux (about the found beads'), and have an axial sd of sqrt(2) planes against the truth's 0."""
    import numpy as np

    import heldout_psf as H
    from cm2cl.analysis import quality as Q

    shape = (96, 96)
    beads = Q.place_beads(16, H.NZ, shape, seed=5, planes=[*range(0, 8), *range(14, 18)], margin=8, min_lateral=8,
                           min_axial=H.NZ)
    beads = beads[np.argsort(beads[:, 0], kind="stable")]     # no bead in another's window (+-3 px)
    near, far = beads[beads[:, 0] < 8], beads[beads[:, 0] >= 14]
    truth = Q.bead_volume(beads, np.random.default_rng(1).uniform(0.5, 1.0, len(beads)), H.NZ, shape)
    vol = truth.copy()
    for z, y, x in far:
        blob = truth[z, y - 1:y + 2, x - 1:x + 2].copy()
        vol[z, y - 1:y + 2, x - 1:x + 2] = 0.0
        for dz in range(-2, 3):
            vol[z + dz, y - 1:y + 2, x - 1:x + 2] += blob / 5
    s = Q.score_beads(vol, beads)
    assert s["matched"] == list(range(len(near)))
    rows = H.spread_rows(vol, truth, beads, s["matched"])
    missed = [r for r in rows if not r["found"]]
    assert len(missed) == len(far) and all(r["plane"] >= 14 for r in missed)
    assert all(r["peak"] < Q.DETECT_REL for r in missed)
    np.testing.assert_allclose([r["flux"] for r in missed], [r["true_flux"] for r in missed], rtol=0.3)
    np.testing.assert_allclose([r["axial_sd"] for r in missed], np.sqrt(2), rtol=1e-9)
    assert max(r["true_axial_sd"] for r in rows) < 1e-12
    table = "\n".join(H.spread_table([{"spread": rows}]))
    assert "| 14-19 (8-13 out) | missed | %d | " % len(far) in table and "| 1.41 (0.00) | " in table


def test_refine_words_say_which_answer_auto_kept():
    """The tables of heldout_psf and random_scenes say what the PSF refinement did, and where 'auto' solved both
    answers, which one it kept."""
    from benchlib import refine_words

    assert refine_words(None) == "-"
    assert refine_words({"mode": "auto", "rounds": 1}) == "auto, 1 round"
    both = {"lenslets": {"rms": 2.0}, "common": {"rms": 1.0}, "kept": "common"}
    assert refine_words({"mode": "auto", "rounds": 2, "compared": both}) == "auto, 2 rounds (common kernel kept of both)"
    assert refine_words({"mode": "auto", "rounds": 12, "compared": {**both, "kept": "lenslets"}}) == \
        "auto, 12 rounds (kernels per lenslet kept of both)"


def test_reproduce_paper_calls_an_axial_width_at_the_fits_floor_a_bound():
    """A region whose median source fills one plane (its axial FWHM is the Gaussian fit's floor, 0.71 plane) is
    reported as a bound with the plane named, not as a width narrower than the paper's; a resolved region keeps
    the general reason; a region within 15% of the paper gives none."""
    import reproduce_paper as RP

    def stats(axial_um, at_floor):
        return {"n_fit": 10, "fwhm_axial_um": {"median": axial_um}, "fwhm_lateral_um": {"median": 11.0},
                "axial_median_at_floor": at_floor, "lateral_median_at_floor": False}

    res = {"binning": 1, "sources": 30, "found": 30, "step_mm": 1.0, "shape": (1944, 2592), "object_pixel_um": 5.28,
           "dz_um": 20.0, "iterations": 700,
           "summary": {"regions": {"central": stats(14.1, True), "outer": stats(70.0, False),
                                   "corner": stats(290.0, False)}}}
    rows = []
    RP._fwhm_rows(lambda name, paper, ours, how, unit="", why="": rows.append((name, ours, why)), res,
                  RP.PAPER_BEADS, "10-um beads", "10 um", "GENERAL", "--bead-bin")
    axial = {name.split(", ")[1].split(" ")[0]: (ours, why) for name, ours, why in rows if name.startswith("axial")}
    assert axial["central"][0] == 14.1 and "fit's floor" in axial["central"][1]
    assert "one 20-um plane" in axial["central"][1] and "bounds the width" in axial["central"][1]
    assert axial["outer"][1] == "GENERAL"                     # resolved, 76% below the paper: the general reason
    assert axial["corner"][1] == ""                           # 290 against 299: within 15%


def test_a_regenerated_page_keeps_its_hand_written_sections(tmp_path):
    """Tools that rewrite a docs page (fit_optics, heldout_psf) keep everything from its first hand-written
    heading on, and write only the generated text on a new page or one without such a heading."""
    from benchlib import with_hand_written

    page = tmp_path / "page.md"
    assert with_hand_written("new\n", page) == "new\n"
    hand = "## Reading (hand-written, stop 9)\n\nkept\n\n## Later\n\nkept too\n"
    page.write_text("# T\n\nold table\n\n## Scan\n\nrows\n\n" + hand)
    assert with_hand_written("new\n", page) == "new\n\n" + hand
    page.write_text("# T\n\nold table, the word hand-written in a line\n")
    assert with_hand_written("new\n", page) == "new\n"
    # every tool that rewrites a page with hand-written sections goes through it (reproduce_paper and
    # diffusercam3d wrote their pages whole, which would have deleted the sections hand-written below)
    tools = Path(__file__).resolve().parents[1] / "tools"
    for name in ("fit_optics", "heldout_psf", "relaxation_study", "reproduce_paper", "diffusercam3d"):
        assert "with_hand_written(" in (tools / f"{name}.py").read_text(), name
    # reproduce_paper's generated PCC-map section lies above the hand-written ones (below, a regeneration would
    # keep the old one as if hand-written)
    text = (Path(__file__).resolve().parents[1] / "docs" / "paper_comparison.md").read_text()
    assert 0 < text.index("## The lateral PCC map") < text.index("(hand-written")
