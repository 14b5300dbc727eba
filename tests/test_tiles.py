"""Lateral tiles (issue 9 item 4): on a scene whose PSF is small against the field, tiles + halo match the
whole solve inside the tiles, leave no seam, cover the sensor once; the planner refuses windows that
would lose views."""

import json

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import cm2cl
from cm2cl import reference as ref
from cm2cl.errors import InputError
from cm2cl.jobs.tiles import operator_norm, plan_tiles, reconstruct_tiled, tile_weights

M = (96, 120)


def scene(seed=3, nz=3):
    """A compact array PSF per plane (three foci within +-7 px of the axis, spacing changing with depth) and
    30 beads, Poisson-like noise."""
    rng = np.random.default_rng(seed)
    psf = np.zeros((nz,) + M)
    cy, cx = M[0] // 2, M[1] // 2
    for i in range(nz):
        d = 3 + 2 * i
        for dy, dx in ((0, 0), (d, -d), (-d, d)):
            psf[i, cy + dy, cx + dx] = 1.0
        psf[i] = gaussian_filter(psf[i], 0.8)
    psf /= psf.reshape(nz, -1).sum(axis=1)[:, None, None]
    P = (2 * M[0], 2 * M[1])
    x = np.zeros((nz,) + P)
    oy, ox = (P[0] - M[0]) // 2, (P[1] - M[1]) // 2
    for _ in range(30):
        x[rng.integers(nz), oy + rng.integers(4, M[0] - 4), ox + rng.integers(4, M[1] - 4)] = rng.uniform(0.5, 1.0)
    y = ref.forward(psf, x, P)
    y = y + 0.01 * y.max() * rng.standard_normal(y.shape)
    return psf, y


# each tile would fit a background of its own; TV on, as the tiles' halos were sized for it
KW = dict(max_iter=80, tol=0, background="none", tv_noise_ratio=30.0, l1_noise_ratio=30.0, l1_plane_power=0.0)


def test_tiles_match_the_whole_solve_without_seams(rt):
    psf, y = scene()
    # 800 iterations: each tile's solve rebalances its own penalties (x1.5 steps to iteration 100), so the
    # paths part early and meet again near the answer (seen 4.9% apart at 80 iterations, 0.7% at 800)
    kw = {**KW, "max_iter": 800}
    whole = cm2cl.reconstruct(y, psf, **kw, psf_refine=0).volume.astype(np.float64)
    tiled, info = reconstruct_tiled(y, psf, (48, 60), **kw)
    assert info["tiles"] == 4 and info["halo"] == info["reach"] and info["reach"][0] <= 12
    assert info["l1"] == pytest.approx(cm2cl.reconstruct(y, psf, **{**KW, "max_iter": 1}, psf_refine=0).info["l1"], rel=1e-6)
    # inside the tiles, away from the sensor's edge (where both solves see the same unknown boundary
    # differently padded): the tiled volume is the whole solve's within 1.5% (seen: 0.7%; the halo keeps
    # the windows' own edges out, but ADMM on another grid does not give the same iterates)
    e = 8
    a, b = tiled[:, e:-e, e:-e], whole[:, e:-e, e:-e]
    err = np.linalg.norm(a - b) / np.linalg.norm(b)
    print(f"tiled vs whole relative error {err:.3e}")
    assert err < 1.5e-2, err
    # no seam: the mean lateral gradient across the tile borders is no larger than inside the tiles
    mip = tiled.sum(axis=0)
    gy = np.abs(np.diff(mip, axis=0))    # gy[r] = |mip[r + 1] - mip[r]|
    gx = np.abs(np.diff(mip, axis=1))
    across = np.concatenate([gy[47, e:-e], gx[e:-e, 59]])
    inside = np.concatenate([gy[e:40, e:-e].ravel(), gy[56:-e, e:-e].ravel(), gx[e:-e, e:52].ravel(),
                             gx[e:-e, 68:-e].ravel()])
    print(f"mean gradient across borders {across.mean():.3e}, inside {inside.mean():.3e}")
    assert across.mean() <= 1.5 * inside.mean()
    # and the seam check can fail: tiles solved with their own weights and scales (each tile normalised
    # by its own maximum, weights from its own noise estimate) differ from the whole solve far more
    own = np.zeros_like(tiled, dtype=np.float64)
    for ((r0, r1), (c0, c1)) in [((0, 48), (0, 60)), ((0, 48), (60, 120)), ((48, 96), (0, 60)), ((48, 96), (60, 120))]:
        own[:, r0:r1, c0:c1] = cm2cl.reconstruct(y[r0:r1, c0:c1], psf[:, 24:72, 30:90], **kw, psf_refine=0).volume
    err_own = np.linalg.norm(own[:, e:-e, e:-e] - b) / np.linalg.norm(b)
    assert err_own > 3 * err, (err_own, err)


def test_tile_weights_cover_the_sensor_once():
    psf, _ = scene()
    plan = plan_tiles(M, psf, (30, 50))
    total = np.zeros(M)
    for ((a, b), (c, d)), w in tile_weights(plan):
        assert w.min() >= 0
        total[a:b, c:d] += w
    np.testing.assert_allclose(total, 1.0)
    assert len(plan.tiles) == 4 * 3


def test_planner_refuses_windows_that_lose_views():
    psf, y = scene()
    reach = plan_tiles(M, psf, (48, 60)).reach
    with pytest.raises(InputError, match=r"halo: 2 x 2 px is smaller than the PSF's reach"):
        plan_tiles(M, psf, (48, 60), halo=2)
    with pytest.raises(InputError, match=r"smaller than the PSF's spread"):
        plan_tiles(M, psf, (reach[0] // 2, reach[1] // 2))    # the sensor's corner tiles: window < 2 reach + 1
    with pytest.raises(InputError, match="tile: expected two positive integers"):
        plan_tiles(M, psf, (0, 10))
    # issue 27 F12: a PSF whose light spans the field (corners and centre) makes every window of 2 x 2
    # tiles 94 of 96 px wide: each tile would solve about the whole frame
    full = np.zeros((2, 96, 96))
    full[:, [2, 2, 48, 93, 93], [2, 93, 48, 2, 93]] = 1.0
    with pytest.raises(InputError, match=r"a window of 94 x 94 px \(tile \+ a halo of 46 x 46 px; the PSF reaches "
                                         r"46 x 46 px from its axis\) covers nearly all of the 96 x 96 px field"):
        plan_tiles((96, 96), full, (48, 48))
    assert len(plan_tiles((96, 96), full, (96, 96)).tiles) == 1    # one tile is the whole frame: allowed
    with pytest.raises(InputError, match="padded_shape: not available with lateral tiles"):
        reconstruct_tiled(y, psf, (48, 60), padded_shape=(10, 10))


def test_cli_tiles_and_their_plan(rt, tmp_path, capsys):
    """`cm2cl reconstruct --tile TY TX`: the dry run prints the tile plan, the run writes the blended
    volume (the Python function's), a halo below the PSF's reach is refused before any output."""
    import tifffile

    from cm2cl import io
    from cm2cl.cli import main

    psf, y = scene()
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", y.astype(np.float32))
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--max-iter", "20",
            "--tol", "0", "--quiet", "--tile", "48", "60"]
    assert main(base + ["-o", str(tmp_path / "t.ome.tif"), "--dry-run"]) == 0
    assert "tiles: 4 tiles of 48 x 60 px with a halo of" in capsys.readouterr().out
    assert main(base + ["-o", str(tmp_path / "t.ome.tif")]) == 0
    vol = io.read_tiff(tmp_path / "t.ome.tif")[0]
    expect, _ = reconstruct_tiled(y.astype(np.float32), psf.astype(np.float32), (48, 60), max_iter=20, tol=0)
    np.testing.assert_allclose(vol, expect, rtol=1e-5, atol=1e-6 * expect.max())
    info = json.loads((tmp_path / "t.cm2cl.json").read_text())["info"]
    tiles = info["tile_misfits"]   # each tile's data misfit over its window; the record's is the worst tile's
    assert len(tiles) == 4 and all(m["ratio"] > 0 for m in tiles)
    assert info["misfit"] == max(tiles, key=lambda m: m["ratio"])
    capsys.readouterr()
    assert main(base + ["-o", str(tmp_path / "u.ome.tif"), "--halo", "2"]) == 2
    assert "halo: 2 x 2 px is smaller than the PSF's reach" in capsys.readouterr().err
    assert not (tmp_path / "u.ome.tif").exists()


def test_operator_norm_is_the_largest_singular_value():
    """The whole frame's ||H|| that the tiles divide by: the largest singular value of x -> sum_i h_i * x_i
    (circular on the 2M - 1 grid), from a dense matrix; for a stack with negative values (offset
    subtracted) too, where the f = 0 shortcut of a non-negative stack would be wrong."""
    import scipy.fft as sfft

    rng = np.random.default_rng(7)
    nz, my, mx = 2, 5, 6
    grid = tuple(sfft.next_fast_len(2 * m - 1, real=True) for m in (my, mx))
    signed = rng.random((nz, my, mx))
    signed -= 0.9 * signed.mean(axis=(1, 2), keepdims=True)     # little left at f = 0
    for h in (rng.random((nz, my, mx)), signed):
        cols = []
        for i in range(nz):
            for k in range(grid[0] * grid[1]):
                e = np.zeros(grid)
                e.flat[k] = 1.0
                pad = np.zeros(grid)
                pad[:my, :mx] = h[i]
                cols.append(np.real(np.fft.ifft2(np.fft.fft2(pad) * np.fft.fft2(e))).ravel())
        sigma = np.linalg.svd(np.array(cols).T, compute_uv=False)[0]
        assert abs(operator_norm(h) - sigma) < 1e-9 * sigma
    assert np.sqrt(np.sum(signed.sum(axis=(1, 2)) ** 2)) < 0.8 * operator_norm(signed)   # the f = 0 shortcut fails
