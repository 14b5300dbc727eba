"""The lateral PCC map (paper Fig. 2C, S4C): registration of truncated arrays, the PCC against values computed
here from the known alignment, the foci and regions against the optics' geometry, and the command."""

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from cm2cl.analysis.lateral import count_foci, high_pcc_diameter_mm, lateral_pcc_map, region_summary

SHAPE = (120, 150)
SEP = 30                 # px between foci
STEP = 12                # px the array moves per grid step (foci move together at one depth)


def _spot(shape, cy, cx, sigma=1.5, amp=1.0, elong=1.0):
    y, x = np.mgrid[:shape[0], :shape[1]]
    return amp * np.exp(-0.5 * (((y - cy) / sigma) ** 2 + ((x - cx) / (sigma * elong)) ** 2))


def _array(dy, dx, amps, central_elong=1.0):
    """A 3 x 3 array of Gaussian foci, lenslet k of amplitude amps[k], moved by (dy, dx) px; foci whose centre
    leaves the sensor are cut (as the finite sensor cuts them)."""
    img = np.zeros(SHAPE)
    k = 0
    for r in (-1, 0, 1):
        for c in (-1, 0, 1):
            cy, cx = SHAPE[0] // 2 + r * SEP + dy, SHAPE[1] // 2 + c * SEP + dx
            if 0 <= cy < SHAPE[0] and 0 <= cx < SHAPE[1]:
                img += _spot(SHAPE, cy, cx, amp=amps[k], elong=central_elong if (r, c) == (0, 0) else 1.0)
            k += 1
    return img


def _pearson(a, b):
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def _shift_zero(img, dy, dx):
    out = np.zeros_like(img)
    src = img[max(0, -dy):img.shape[0] - max(0, dy), max(0, -dx):img.shape[1] - max(0, dx)]
    out[max(0, dy):max(0, dy) + src.shape[0], max(0, dx):max(0, dx) + src.shape[1]] = src
    return out


@pytest.fixture(scope="module")
def scan():
    """7 x 9 positions; lenslets of unequal brightness (so that aligning a truncated array with the wrong block
    of the reference changes the PCC), the outer positions lose rows or columns of foci."""
    amps = np.random.default_rng(3).uniform(0.5, 1.5, 9)
    ny, nx = 7, 9
    grid = np.zeros((ny, nx) + SHAPE)
    moves = np.zeros((ny, nx, 2), int)
    for i in range(ny):
        for j in range(nx):
            moves[i, j] = ((i - ny // 2) * STEP, (j - nx // 2) * STEP)
            grid[i, j] = _array(*moves[i, j], amps)
    return grid, moves, amps


def test_registration_and_pcc_of_truncated_arrays(scan):
    grid, moves, _ = scan
    m = lateral_pcc_map(grid, central=False)
    # the registration undoes each move, also where foci were lost and several alignments look alike
    assert np.array_equal(m["shifts"], -moves)
    ref = grid[3, 4]
    for i in range(grid.shape[0]):
        for j in range(grid.shape[1]):
            want = _pearson(ref, _shift_zero(grid[i, j], *(-moves[i, j])))
            assert m["pcc"][i, j] == pytest.approx(want, abs=1e-9)
    assert m["pcc"][3, 4] == pytest.approx(1.0, abs=1e-12)
    # foci per position: 9 inside, 6 where a row or a column left the sensor, 4 at the corners
    assert m["views"][3, 4] == 9 and m["views"][0, 4] == 6 and m["views"][3, 0] == 6 and m["views"][0, 0] == 4
    assert m["regions"][3, 4] == "central" and m["regions"][0, 4] == "outer" and m["regions"][0, 0] == "corner"
    s = region_summary(m)
    assert s["central"]["pcc_mean"] > s["outer"]["pcc_mean"] > s["corner"]["pcc_mean"]


def test_shift_invariant_scan_is_one_everywhere():
    amps = np.ones(9)
    grid = np.stack([np.stack([_array(dy, dx, amps) for dx in (-4, 0, 4)]) for dy in (-3, 0, 3)])
    m = lateral_pcc_map(grid)
    assert np.allclose(m["pcc"], 1.0, atol=1e-9) and np.allclose(m["pcc_central"], 1.0, atol=1e-9)
    assert (m["views"] == 9).all() and (m["regions"] == "central").all()


def test_central_map_sees_the_central_lenslet_alone():
    """Only the central focus differs (elongated, as an off-axis aberration makes it): the central map drops
    there and stays 1 elsewhere; the whole-array map drops less (8 of 9 foci still agree)."""
    amps = np.ones(9)
    ys, xs = np.arange(-2, 3) * 0.2, np.arange(-2, 3) * 0.2
    grid = np.stack([np.stack([_array(int(i * 10), int(j * 10), amps, central_elong=1.0 + (abs(i) > 0.3) * 1.5)
                               for j in xs]) for i in ys])
    m = lateral_pcc_map(grid, xs, ys)
    assert m["ref"] == (2, 2)
    blurred = np.abs(ys)[:, None] > 0.3
    blurred = np.broadcast_to(blurred, m["pcc"].shape)
    assert np.allclose(m["pcc_central"][~blurred], 1.0, atol=1e-9)
    assert (m["pcc_central"][blurred] < 0.95).all()
    assert (m["pcc"][blurred] > m["pcc_central"][blurred]).all()
    # the region above 0.7 is the middle three rows: 15 positions of 0.2 x 0.2 mm
    d = high_pcc_diameter_mm({**m, "pcc_central": np.where(blurred, 0.5, 1.0)})
    assert d == pytest.approx(2 * np.sqrt(15 * 0.04 / np.pi))


def test_foci_of_the_model_agree_with_its_geometry():
    """The foci counted in the model's images equal the views its geometry predicts (sensor edge and the
    pixels' 21-degree angular cutoff)."""
    from cm2cl.optics import CM2Optics, array_psf
    from cm2cl.optics.geometry import view_count

    o = CM2Optics(binning=8)
    for x, y in [(0, 0), (2.0, 0.5), (3.6, 0), (0, 2.2), (3.6, 2.2), (4.8, 0.0), (-3.6, -2.2)]:
        img = array_psf(o, 0.0, x, y, cutoff_deg=21.0)
        assert count_foci(img) == view_count(o, 0.0, x, y, cutoff_deg=21.0), (x, y)


def test_pcc_map_command(tmp_path, scan):
    from cm2cl.io.tiff import write_tiff

    grid, moves, _ = scan
    f = tmp_path / "scan.ome.tif"
    ys, xs = (np.arange(7) - 3) * 0.25, (np.arange(9) - 4) * 0.25
    write_tiff(f, grid.reshape(-1, *SHAPE).astype(np.float32),
               extra={"kind": "lateral_psf_grid", "grid_shape": [7, 9], "x_mm": xs, "y_mm": ys})
    out = tmp_path / "map"
    r = subprocess.run([sys.executable, "-m", "cm2cl", "analyze", "pcc-map", str(f), "-o", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rec = json.loads((out / "analysis.json").read_text())
    assert rec["grid_shape"] == [7, 9] and rec["unit"] == "mm" and rec["reference"] == [3, 4]
    rows = list(csv.DictReader(open(out / "pcc_map.csv")))
    assert len(rows) == 63
    direct = lateral_pcc_map(grid.astype(np.float32).astype(np.float64), xs, ys)
    for row in rows:
        i, j = int(row["grid_row"]), int(row["grid_col"])
        assert float(row["pcc"]) == pytest.approx(direct["pcc"][i, j], abs=1e-9)
        assert float(row["y_mm"]) == pytest.approx(ys[i]) and float(row["x_mm"]) == pytest.approx(xs[j])
        assert int(row["views"]) == direct["views"][i, j]
    assert rec["regions"]["central"]["positions"] == int((direct["views"] == 9).sum())
    # a plain stack needs its grid; a wrong grid or step is refused before any output
    raw = tmp_path / "raw.tif"
    import tifffile
    tifffile.imwrite(raw, grid.reshape(-1, *SHAPE).astype(np.float32))
    for extra, words in ((["--grid", "7,8"], "63 PSFs"), ([], "--grid NY,NX"), (["--grid", "7,9", "--step-mm", "0"],
                                                                                "must be positive"),
                         (["--grid", "7,9", "--ref", "9,0"], "outside")):
        bad = tmp_path / "bad"
        r = subprocess.run([sys.executable, "-m", "cm2cl", "analyze", "pcc-map", str(raw), "-o", str(bad)] + extra,
                           capture_output=True, text=True)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not bad.exists()
