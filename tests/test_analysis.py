"""Figures of merit: PCC with registration, widths, SBR, MIP figures, emitter detection/matching."""

import numpy as np
import pytest

from cm2cl import analysis as an
from cm2cl.analysis import metrics
from cm2cl.errors import InputError


def gaussian_blob(shape, centre, sigma):
    grids = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    r2 = sum(((g - c) / s) ** 2 for g, c, s in zip(grids, centre, sigma))
    return np.exp(-0.5 * r2)


def test_pcc_is_eq5_and_registration_undoes_shifts():
    rng = np.random.default_rng(0)
    a = np.zeros((64, 80))
    a[20:30, 10:50] = rng.random((10, 40))
    assert an.pcc(a, a) == pytest.approx(1.0)
    assert an.pcc(a, -a, register=False) == pytest.approx(-1.0)
    b = metrics._shift_zero(a, 5, -7)
    assert an.register_shift(a, b) == (-5, 7)
    assert an.pcc(a, b) == pytest.approx(1.0)
    assert an.pcc(a, b, register=False) < 0.5
    # Eq. 5 against numpy's corrcoef
    c = a + 0.3 * rng.random(a.shape)
    assert an.pcc(a, c, register=False) == pytest.approx(np.corrcoef(a.ravel(), c.ravel())[0, 1])
    # search window
    assert an.register_shift(a, b, max_shift=3) != (-5, 7)


def test_axial_pcc_and_width_at_level():
    z = np.arange(-10, 11) * 10.0
    # a spot that shifts (undone by registration) and widens (not undone) with |z|
    stack = np.stack([gaussian_blob((48, 48), (24, 24 + 0.5 * zz / 10), (1.5 + abs(zz) / 40,) * 2) for zz in z])
    curve = an.axial_pcc(stack, ref_index=10)
    assert curve[10] == pytest.approx(1.0)
    assert np.all(np.diff(curve[10:]) < 0) and np.all(np.diff(curve[:11]) > 0)
    assert curve[-1] < 0.8
    # triangle: known crossings
    x = np.linspace(-5, 5, 11)
    v = 1 - np.abs(x) / 5
    assert an.width_at_level(x, v, 0.8) == pytest.approx(2.0)
    with pytest.raises(InputError, match="does not fall below"):
        an.width_at_level(x[5:], v[5:], 0.1)


def test_fwhm_of_a_gaussian():
    x = np.arange(101)
    prof = 3.0 * np.exp(-0.5 * ((x - 50.3) / 6.0) ** 2) + 1.0
    assert an.fwhm(prof, spacing=0.5, baseline="min") == pytest.approx(0.5 * 2.3548 * 6.0, rel=0.01)


def test_local_sbr():
    img = np.full((40, 40), 2.0)
    mask = np.zeros_like(img, bool)
    mask[5:10, 5:10] = True          # patch (0, 0)
    mask[25:30, 25:30] = True        # patch (1, 1)
    img[mask] = 6.0
    img[20:, 20:] += 2.0             # brighter background in patch (1, 1)
    sbr, mean = an.local_sbr(img, mask, 20)
    assert sbr[0, 0] == pytest.approx(3.0)
    assert sbr[1, 1] == pytest.approx(2.0)
    assert np.isnan(sbr[0, 1])
    assert mean == pytest.approx(2.5)
    m = an.signal_mask(img - 2.0, 0.5)
    assert m[7, 7] and not m[0, 0]


def test_find_and_match_emitters_subvoxel():
    rng = np.random.default_rng(3)
    shape = (9, 64, 64)
    true = np.array([[2.3, 10.4, 12.7], [6.6, 40.2, 50.5], [4.0, 30.8, 20.1]])
    vol = sum(gaussian_blob(shape, c, (0.8, 1.2, 1.2)) for c in true)
    vol += 0.01 * rng.random(shape)
    det = an.find_emitters(vol, threshold=0.3, voxel_size_um=(100.0, 5.0, 5.0))
    assert len(det["amplitude"]) == 3
    res = an.match_emitters(det["position_um"], true * np.array([100.0, 5.0, 5.0]), 20.0, 150.0)
    assert res["n_matched"] == 3 and res["recall"] == 1.0 and res["precision"] == 1.0
    assert res["lateral_rms_um"] < 1.0        # 0.2 voxel
    assert res["axial_rms_um"] < 15.0         # 0.15 plane
    # a far-away detection does not match
    res2 = an.match_emitters(np.array([[0.0, 1000.0, 1000.0]]), true, 20.0, 150.0)
    assert res2["n_matched"] == 0 and res2["recall"] == 0.0
    # depths_um map the axial index
    det2 = an.find_emitters(vol, threshold=0.3, depths_um=np.linspace(-400, 400, 9))
    assert np.sort(det2["position_um"][:, 0])[0] == pytest.approx(-400 + 2.3 * 100, abs=15)


def _mip_panels(img):
    """(rows, cols) slices of the XY, YZ and XZ panels of a mip_png figure, found in the image: the
    panels are black (no signal) and touch, XY top-left, YZ to its right, XZ below it. An opening
    removes the tick marks, which are black too and stick out of the panels."""
    from scipy import ndimage
    dark = ndimage.binary_opening(img.max(axis=2) < 0.05, structure=np.ones((7, 7)))
    lab, n = ndimage.label(dark)
    big = 1 + int(np.argmax(ndimage.sum(dark, lab, range(1, n + 1))))
    block = lab == big
    rows, cols = np.nonzero(block)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    cx = c0 + int(np.nonzero(block[r1 - 1, c0:c1])[0].max()) + 1      # XZ (bottom) is as wide as XY
    ry = r0 + int(np.nonzero(block[r0:r1, c1 - 1])[0].max()) + 1      # YZ (right) is as tall as XY
    return {"xy": (slice(r0, ry), slice(c0, cx)), "yz": (slice(r0, ry), slice(cx, c1)),
            "xz": (slice(ry, r1), slice(c0, cx))}


def test_mip_png_shows_a_bright_voxel_at_its_place_in_each_panel(tmp_path):
    """One bright voxel (z=3, y=6, x=30) of a (5, 30, 40) volume: the brightest pixel of each panel is
    where that voxel projects (XY: row y, col x; YZ: row y, col z; XZ: row z, col x), coloured with the
    depth colour of plane 3, and nothing else in the panels is lit."""
    from matplotlib import colormaps
    from matplotlib.image import imread
    nz, ny, nx = 5, 30, 40
    z, y, x = 3, 6, 30
    vol = np.zeros((nz, ny, nx))
    vol[z, y, x] = 1.0
    p = an.mip_png(vol, tmp_path / "mip.png", voxel_size_um=(100, 5, 5), depths_um=[-200, -100, 0, 100, 200],
                   title="test")
    img = imread(p)[..., :3]
    panels = _mip_panels(img)
    # (row fraction, col fraction) of the voxel centre in each panel; z runs left->right (YZ), down (XZ)
    where = {"xy": ((y + 0.5) / ny, (x + 0.5) / nx), "yz": ((y + 0.5) / ny, (z + 0.5) / nz),
             "xz": ((z + 0.5) / nz, (x + 0.5) / nx)}
    colour = colormaps["turbo"](z / (nz - 1))[:3]
    for name, (rs, cs) in panels.items():
        panel = img[rs, cs]
        h, w = panel.shape[:2]
        fr, fc = where[name]
        er, ec = fr * h, fc * w
        lit = panel.max(axis=2) > 0.3
        r, c = np.nonzero(lit)
        assert lit.any(), name
        # the lit pixels form one spot, centred on the voxel (within half a voxel of the panel's grid)
        half_r = 0.5 * h / {"xy": ny, "yz": ny, "xz": nz}[name] + 1
        half_c = 0.5 * w / {"xy": nx, "yz": nz, "xz": nx}[name] + 1
        assert abs(r.mean() - er) < half_r and abs(c.mean() - ec) < half_c, (name, r.mean(), er, c.mean(), ec)
        assert np.ptp(r) <= 2 * half_r + 1 and np.ptp(c) <= 2 * half_c + 1, name
        assert np.allclose(panel[int(er), int(ec)], colour, atol=0.02), (name, panel[int(er), int(ec)], colour)


def test_bad_inputs():
    with pytest.raises(InputError, match="shapes differ"):
        an.pcc(np.zeros((3, 3)), np.zeros((3, 4)))
    with pytest.raises(InputError, match="constant"):
        an.pcc(np.ones((3, 3)), np.ones((3, 3)), register=False)
    with pytest.raises(InputError, match="mask shape"):
        an.local_sbr(np.ones((4, 4)), np.ones((3, 3), bool), 2)


def test_content_region():
    vol = np.zeros((2, 50, 60))
    vol[1, 20, 30] = 1.0
    vol[0, 25, 40] = 0.5
    rs, cs = an.content_region(vol, margin=3)
    assert (rs.start, rs.stop, cs.start, cs.stop) == (17, 29, 27, 44)
    assert an.content_region(np.zeros((1, 4, 5))) == (slice(0, 4), slice(0, 5))


def test_mip_png_labels_pixels_as_pixels_and_um_only_with_a_scale(tmp_path, monkeypatch):
    """A volume without a physical scale is labelled in px and planes (not um); with voxel sizes the axes
    read um and span the volume's extent (x to nx * dx); depths without a lateral scale are refused."""
    from matplotlib.figure import Figure
    figs = []
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: figs.append(self))
    vol = np.zeros((4, 20, 30))
    vol[1, 5, 7] = 1.0
    an.mip_png(vol, tmp_path / "a.png")
    an.mip_png(vol, tmp_path / "b.png", voxel_size_um=(50, 5, 5), depths_um=[-100, -50, 0, 50])
    labels = [sorted(ax.get_xlabel() + ax.get_ylabel() for ax in f.axes) for f in figs]
    assert "x (px)z (plane)" in labels[0] and not any("um" in s for s in labels[0])
    assert "x (um)z (um)" in labels[1]
    xz = [ax for ax in figs[1].axes if ax.get_xlabel() == "x (um)"][0]
    assert xz.get_images()[0].get_extent()[:2] == [0.0, 150.0]
    with pytest.raises(InputError, match="depths_um"):
        an.mip_png(vol, tmp_path / "c.png", depths_um=[0, 1, 2, 3])


def test_mip_png_scale_bar_reads_back_in_um(tmp_path, monkeypatch):
    """With a voxel size the figure carries a scale bar of a round length near a fifth of the field, drawn on
    the XZ panel's x scale, and the PNG records the axes' units and the bar (text chunks other programs
    read); without one, neither a bar nor um."""
    from matplotlib.figure import Figure
    from PIL import Image

    vol = np.zeros((4, 20, 30))
    vol[1, 5, 7] = 1.0
    a = an.mip_png(vol, tmp_path / "a.png")
    b = an.mip_png(vol, tmp_path / "b.png", voxel_size_um=(50, 44, 44))      # 1320 um wide: a 200-um bar
    ta, tb = Image.open(a).text, Image.open(b).text
    assert ta["cm2cl:axes"] == "x (px), y (px), z (plane)" and "cm2cl:scale_bar_um" not in ta
    assert tb["cm2cl:axes"] == "x (um), y (um), z (um)" and float(tb["cm2cl:scale_bar_um"]) == 200.0
    assert [an.scale_bar_um(w) for w in (1320, 999, 5000, 7.3)] == [200.0, 100.0, 1000.0, 1.0]
    figs = []
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: figs.append(self))
    an.mip_png(vol, tmp_path / "c.png", voxel_size_um=(50, 44, 44))
    xz = [ax for ax in figs[0].axes if ax.get_xlabel() == "x (um)"][0]
    (bar,) = [ln for ln in xz.get_lines()]
    assert np.ptp(bar.get_xdata()) == pytest.approx(200.0) and max(bar.get_xdata()) == pytest.approx(1320.0)
    assert any(t.get_text() == "200 um" for t in xz.texts)
