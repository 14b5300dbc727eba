"""cm2cl analyze mtf (issue 25): the 3D MTF of an axial stack, its support, the lateral cutoff, the axial
bandwidth along f_x and the 3D SBP from the measured bandwidths, against stacks whose spectra are known."""

import csv
import json
import math

import numpy as np
import pytest

from cm2cl import io
from cm2cl.analysis.mtf import axial_extent, lateral_cutoff, mtf_3d, mtf_analysis
from cm2cl.cli import main

DZ, DX = 10.0, 2.0


def _box_stack(shape=(32, 48, 48), kz=5, kx=7):
    """A stack whose spectrum is 1 on |fz| <= kz bins, |fy|, |fx| <= kx bins and 0 elsewhere."""
    f = [np.abs(np.fft.fftfreq(n) * n) for n in shape]
    spec = (f[0][:, None, None] <= kz) & (f[1][None, :, None] <= kx) & (f[2][None, None, :] <= kx)
    return np.real(np.fft.ifftn(spec.astype(float)))


def _tilted_lines(tan_a=0.3, sigma=1.2, sz=60.0, shape=(64, 64, 96), lines=(-1, 0, 1)):
    """Gaussian spots (sigma px) at x = k z tan(a) for each k in ``lines``, brightness exp(-z^2 / 2 sz^2)."""
    nz, ny, nx = shape
    z = (np.arange(nz) - nz // 2) * DZ
    yy, xx = (np.mgrid[:ny, :nx] - np.array([ny // 2, nx // 2])[:, None, None]) * DX
    out = np.zeros(shape)
    for i, zi in enumerate(z):
        for k in lines:
            out[i] += np.exp(-zi ** 2 / (2 * sz ** 2)) * np.exp(-(yy ** 2 + (xx - k * zi * tan_a) ** 2)
                                                                / (2 * (sigma * DX) ** 2))
    return out


def test_box_spectrum_gives_its_band_limits():
    shape, kz, kx = (32, 48, 48), 5, 7
    m = mtf_3d(_box_stack(shape, kz, kx), DZ, DX, DX)
    assert m["mtf"][16, 24, 24] == pytest.approx(1.0)
    dfz, dfx = 1 / (shape[0] * DZ), 1 / (shape[2] * DX)
    fc = lateral_cutoff(m, 0.01)
    assert kx * dfx <= fc < (kx + 1) * dfx                      # the last sample inside, before the first outside
    for k in (0, 3, kx):
        assert axial_extent(m, k * dfx, 0.01) == pytest.approx(2 * kz * dfz)
    assert axial_extent(m, (kx + 2) * dfx, 0.01) == 0.0


def test_gaussian_spot_cutoff_is_the_closed_form():
    """A spot of sigma s has MTF exp(-2 pi^2 s^2 f^2) along f_x: it falls to L at f = sqrt(ln(1/L) / 2) / (pi s)."""
    sigma = 1.5
    m = mtf_3d(_tilted_lines(0.0, sigma=sigma, lines=(0,)), DZ, DX, DX)
    for level in (0.01, 0.1, 0.5):
        want = math.sqrt(math.log(1 / level) / 2) / (math.pi * sigma * DX)
        assert lateral_cutoff(m, level) == pytest.approx(want, rel=0.03)


def test_tilted_bands_widen_the_axial_bandwidth_linearly():
    """Three lines x = 0, +-z tan(a) put bands at f_z = 0, -+tan(a) f_x, each a Gaussian of sigma 1 / (2 pi sz)
    in f_z with amplitude A(f_x) = exp(-2 pi^2 s^2 f_x^2) / 3 of the DC: the support at level L spans
    2 tan(a) f_x + 2 sigma_f sqrt(2 ln(A / L)) (within a sample of f_z on each side)."""
    tan_a, sigma, sz, level = 0.3, 1.2, 60.0, 0.01
    m = mtf_3d(_tilted_lines(tan_a, sigma, sz), DZ, DX, DX)
    dfz = m["fz"][1] - m["fz"][0]
    sf = 1 / (2 * math.pi * sz)
    got = []
    for fx in m["fx"][(m["fx"] > 0.005) & (m["fx"] < 0.05)]:
        a = math.exp(-2 * math.pi ** 2 * (sigma * DX) ** 2 * fx ** 2) / 3
        want = 2 * tan_a * fx + 2 * sf * math.sqrt(2 * math.log(a / level))
        e = axial_extent(m, fx, level)
        assert abs(e - want) <= 2 * dfz, (fx, e, want)
        got.append(e)
    assert np.all(np.diff(got) >= 0) and got[-1] > 2 * got[0]
    one = mtf_3d(_tilted_lines(tan_a, sigma, sz, lines=(0,)), DZ, DX, DX)    # the centre alone: no 2 tan(a) f_x
    a1 = math.exp(-2 * math.pi ** 2 * (sigma * DX) ** 2 * 0.04 ** 2)
    assert abs(axial_extent(one, 0.04, level) - 2 * sf * math.sqrt(2 * math.log(a1 / level))) <= 2 * dfz


def test_sbp_follows_the_measured_bandwidths():
    """SBP = FOV x DOF x B_z B_x^2 / 2 from this stack's own bandwidths: a blurrier spot cuts B_x, B_z and the SBP."""
    sharp = mtf_analysis(_tilted_lines(0.3, 1.0), DZ, DX, DX, fov_mm=(8.1, 7.3), dof_mm=2.5)
    blur = mtf_analysis(_tilted_lines(0.3, 2.0), DZ, DX, DX, fov_mm=(8.1, 7.3), dof_mm=2.5)
    for r in (sharp, blur):
        assert r["lateral_bandwidth_per_um"] == pytest.approx(2 * r["lateral_cutoff_measured_per_um"])
        assert r["sbp"] == pytest.approx(8.1 * 7.3 * 2.5e9 * r["axial_bandwidth_per_um"]
                                         * r["lateral_bandwidth_per_um"] ** 2 / 2)
    assert blur["lateral_bandwidth_per_um"] < 0.6 * sharp["lateral_bandwidth_per_um"]
    assert blur["axial_bandwidth_per_um"] < sharp["axial_bandwidth_per_um"] and blur["sbp"] < 0.3 * sharp["sbp"]
    own = mtf_analysis(_tilted_lines(0.3, 1.0), DZ, DX, DX)      # FOV and DOF of the stack itself
    assert own["fov_mm"] == pytest.approx([64 * DX / 1000, 96 * DX / 1000]) and own["dof_mm"] == pytest.approx(0.63)
    given = mtf_analysis(_tilted_lines(0.3, 1.0), DZ, DX, DX, lateral_cutoff_um=0.05)
    assert given["lateral_cutoff_per_um"] == 0.05 and given["axial_bandwidth_per_um"] == pytest.approx(
        axial_extent(mtf_3d(_tilted_lines(0.3, 1.0), DZ, DX, DX), 0.05, given["floor"]["used"]))


def test_cli_analyze_mtf(tmp_path, capsys):
    stack = _tilted_lines(0.3, 1.2).astype(np.float32)
    z = (np.arange(stack.shape[0]) - 32) * DZ
    io.write_tiff(tmp_path / "psf.ome.tif", stack, voxel_size_um=(DZ, DX, DX), depths_um=z)
    out = tmp_path / "mtf"
    assert main(["analyze", "mtf", str(tmp_path / "psf.ome.tif"), "-o", str(out), "--lateral-fwhm", "12.5",
                 "--fov-mm", "8.1,7.3", "--dof-mm", "2.5"]) == 0
    said = capsys.readouterr().out
    rec = json.loads((out / "analysis.json").read_text())
    assert rec["lateral_cutoff_per_um"] == pytest.approx(0.04) and rec["cutoff_from"] == "--lateral-fwhm"
    assert rec["sbp"] == pytest.approx(8.1 * 7.3 * 2.5e9 * rec["axial_bandwidth_per_um"] * 0.08 ** 2 / 2)
    assert "B_z" in said and rec["fov_given"] and rec["dof_given"]
    with open(out / "mtf.csv") as f:
        table = list(csv.reader(f))
    assert table[0] == ["fx_per_um", "axial_extent_per_um"] and len(table) == 1 + 48
    assert (out / "mtf.png").stat().st_size > 1000


@pytest.mark.parametrize("extra, message", [
    (["--fov-mm", "8.1"], "--fov-mm"), (["--dof-mm", "-1"], "--dof-mm"), (["--floor", "1.5"], "floor"),
    (["--lateral-cutoff", "0.5"], "Nyquist")])
def test_cli_analyze_mtf_refuses_bad_options(tmp_path, capsys, extra, message):
    stack = _tilted_lines(0.3, 1.2, shape=(8, 16, 16)).astype(np.float32)
    io.write_tiff(tmp_path / "psf.ome.tif", stack, voxel_size_um=(DZ, DX, DX), depths_um=np.arange(8) * DZ)
    assert main(["analyze", "mtf", str(tmp_path / "psf.ome.tif"), "-o", str(tmp_path / "o")] + extra) != 0
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


def test_cli_analyze_mtf_needs_even_depths_and_a_pixel_size(tmp_path, capsys):
    stack = _tilted_lines(0.3, 1.2, shape=(8, 16, 16)).astype(np.float32)
    io.write_tiff(tmp_path / "uneven.ome.tif", stack, voxel_size_um=(DZ, DX, DX),
                  depths_um=[0, 10, 20, 35, 40, 50, 60, 70])
    assert main(["analyze", "mtf", str(tmp_path / "uneven.ome.tif"), "-o", str(tmp_path / "o")]) != 0
    assert "evenly spaced" in capsys.readouterr().err
    io.write_tiff(tmp_path / "bare.tif", stack)
    assert main(["analyze", "mtf", str(tmp_path / "bare.tif"), "-o", str(tmp_path / "o")]) != 0
    assert "depths in um" in capsys.readouterr().err
