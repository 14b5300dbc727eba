"""Depth slabs: streamed through one device from host memory, or spread over several devices (here two
sub-devices of this CPU, each with its own context and queue), compute the whole solve's iterates; the
planner fits the memory it is given."""

import numpy as np
import pytest

from cm2cl import reconstruct
from cm2cl.solver import memory
from cm2cl.solver.memory import memory_estimate, plan_layout, streamed_bytes_per_iteration
from cm2cl.errors import DeviceError, InputError

from test_admm import bead_problem


@pytest.fixture(scope="module")
def subdevices(rt):
    import pyopencl as cl

    if rt.caps.compute_units < 2:
        pytest.skip("the device has one compute unit: no sub-devices to split it into")
    try:
        subs = rt.device.create_sub_devices([cl.device_partition_property.EQUALLY, 1])
    except cl.Error as exc:
        pytest.skip(f"device cannot be partitioned: {exc}")
    return subs[:2]


def problem(nz=7, dtype=np.float32):
    emitters = [(z, 5 + 3 * z, 6 + 4 * z) for z in range(nz)]
    psf, _, y = bead_problem(4, nz=nz, emitters=emitters)
    rng = np.random.default_rng(5)
    y = y + 0.01 * y.max() * rng.standard_normal(y.shape)
    # TV on with an axial weight, so the halo planes across slab and device borders matter
    # (the former default weights, 30 x noise for both: the penalties then change within the 25 iterations)
    return psf.astype(dtype), y.astype(dtype), dict(max_iter=25, tol=0, padded_shape=(64, 80), tv_axial_weight=0.7,
                                                    tv_noise_ratio=30.0, l1_noise_ratio=30.0, l1_plane_power=0.0)


def close(a, b, dtype):
    """Relative distance of two solves: float rounding in the order of the depth sums, amplified by at
    most the iteration count (25) times a few: 6e-5 in float32, 1e-12 in float64 (seen on two devices:
    2.3e-5 / 4.6e-14 with the default over-relaxation 1.6, which amplifies rounding ~3x; 7e-6 / 1.3e-14
    without)."""
    tol = 6e-5 if np.dtype(dtype) == np.float32 else 1e-12
    err = np.linalg.norm(a - b) / np.linalg.norm(b)
    print(f"relative distance {err:.2e}")
    assert err < tol, err
    return err


@pytest.mark.parametrize("overlap", [True, False], ids=["double-buffered", "one-buffer"])
def test_streamed_slabs_equal_the_whole_solve(rt, dtype, overlap):
    psf, y, kw = problem(dtype=dtype)
    # penalties rebalanced from the first iteration: within these 25 iterations some must change, so that the
    # iterations where the x step makes its own rhs are exercised too (from iteration 10, none changed here)
    kw = {**kw, "adapt_from": 1}
    whole = reconstruct(y, psf, dtype=dtype, device=rt, **kw, psf_refine=0)
    assert whole.info["layout"] == [{"device": rt.caps.name, "planes": [0, 7], "streamed": False, "lean": False,
                                     "slab_planes": 7, "overlap": False}]
    streamed = reconstruct(y, psf, dtype=dtype, device=rt, stream=True, max_slab_planes=2, overlap=overlap, **kw, psf_refine=0)
    lay = streamed.info["layout"]
    assert lay[0]["streamed"] and lay[0]["slab_planes"] == 2 and streamed.info["slabs"] == 4
    assert lay[0]["overlap"] is overlap
    # the device holds two planes of each volume (two sets of two when double-buffered), not seven
    assert streamed.info["device_bytes"] < (0.8 if overlap else 0.6) * whole.info["device_bytes"]
    # the traffic is what the memory model says (PSF spectra once at setup), plus the one-plane halos of
    # the 4 slabs per iteration: the previous slab's pz for TV finish (3), the next slab's x for the w
    # split (3), and per TV iteration the previous pz (3), the next residual (3) and each slab's first
    # residual plane written back (4); where the x step makes its own rhs (the first iteration, and where
    # the penalties mu_u, mu_w changed from the iteration before), 4V more in and pz's halo (3)
    moved = streamed.info["moved_bytes"]
    mus = list(zip(streamed.history["mu_u"], streamed.history["mu_w"]))
    own = 1 + sum(a != b for a, b in zip(mus[:-1], mus[1:]))
    assert 1 < own < 25   # both paths ran
    model = sum(streamed_bytes_per_iteration(7, (64, 80), dtype, "cl", 2, rhs_ready=r, relaxed=True) * n
                for r, n in ((True, 25 - own), (False, own))) + memory_estimate(7, (64, 80), dtype, "cl")["psf_spectra"]
    halos = (25 * (3 + 3 + 2 * (3 + 3 + 4)) + 3 * own) * 64 * 80 * np.dtype(dtype).itemsize
    assert moved == model + halos, (moved, model, halos)
    close(streamed.volume, whole.volume, dtype)
    np.testing.assert_allclose(streamed.history["objective"], whole.history["objective"], rtol=1e-5)


def test_slabs_over_two_devices_equal_the_whole_solve(rt, subdevices):
    psf, y, kw = problem()
    whole = reconstruct(y, psf, device=rt, **kw)
    two = reconstruct(y, psf, devices=list(subdevices), **kw)
    assert [p["planes"] for p in two.info["layout"]] == [[0, 4], [4, 7]] or \
        [p["planes"] for p in two.info["layout"]] == [[0, 3], [3, 7]]
    close(two.volume, whole.volume, np.float32)
    # both: two devices, each streaming two-plane slabs
    both = reconstruct(y, psf, devices=list(subdevices), stream=True, max_slab_planes=2, **kw)
    assert all(p["streamed"] for p in both.info["layout"])
    close(both.volume, whole.volume, np.float32)


def test_lean_layout_equals_the_whole_solve(rt, dtype, monkeypatch):
    """The lean layout (one slab of x spectra: the x step transforms each slab's rhs twice, the TV prox
    keeps z in g and its residual in that slab, the next slab's first residual plane in r_next) computes
    the whole solve's iterates in less memory, on one device in 4 slabs; with r_next zero instead (TV's
    axial step across the slab borders wrong) it does not."""
    from cm2cl.device.volume import fill
    from cm2cl.solver.parts import Part

    psf, y, kw = problem(dtype=dtype)
    whole = reconstruct(y, psf, dtype=dtype, device=rt, **kw)
    lean = reconstruct(y, psf, dtype=dtype, device=rt, lean=True, **kw)
    lay = lean.info["layout"]
    assert lay[0]["lean"] and not lay[0]["streamed"] and lay[0]["slab_planes"] == 2 and lean.info["slabs"] == 4
    est = memory_estimate(7, (64, 80), dtype, "cl")
    # one spectrum volume less, but for its one slab of two planes and the plane r_next
    saved = whole.info["device_bytes"] - lean.info["device_bytes"]
    assert saved >= est["psf_spectra"] * 5 / 7 - 64 * 80 * np.dtype(dtype).itemsize, (saved, est["psf_spectra"])
    close(lean.volume, whole.volume, dtype)
    np.testing.assert_allclose(lean.history["objective"], whole.history["objective"], rtol=1e-6)
    one = reconstruct(y, psf, dtype=dtype, device=rt, lean=True, max_slab_planes=1, **kw)
    assert one.info["slabs"] == 7
    close(one.volume, whole.volume, dtype)
    monkeypatch.setattr(Part, "keep_first_plane", lambda self, arr, plane: fill(self.rt, self.planes[plane], 0))
    stale = reconstruct(y, psf, dtype=dtype, device=rt, lean=True, **kw)
    err = np.linalg.norm(stale.volume - whole.volume) / np.linalg.norm(whole.volume)
    assert err > 1e-3, err


@pytest.mark.parametrize("extra", [dict(tv=0.0), dict(penalty="balance"), dict(tv_iters=1),
                                   dict(tv_iters=3, tv_isotropic=False)],
                         ids=["tv-off", "balance-penalties", "one-tv-iteration", "three-anisotropic"])
def test_lean_layout_equals_the_whole_solve_across_options(rt, extra):
    """TV off (TV finish reads x, no residual), penalties that change on most iterations (the x step
    makes its own rhs into g, then transforms it twice), one and three TV iterations per x step."""
    psf, y, kw = problem()
    kw["background"] = "none"   # with it the balance case's volume vanishes in 25 iterations (b takes the light)
    whole = reconstruct(y, psf, device=rt, **kw, **extra)
    assert np.linalg.norm(whole.volume) > 0
    lean = reconstruct(y, psf, device=rt, lean=True, **kw, **extra)
    assert lean.info["layout"][0]["lean"]
    close(lean.volume, whole.volume, np.float32)


def test_lean_parts_over_two_devices_equal_the_whole_solve(rt, subdevices):
    """Lean parts on two devices: the residual plane across the device border comes from the next
    part's r_next (its slab 0, visited last)."""
    psf, y, kw = problem()
    whole = reconstruct(y, psf, device=rt, **kw)
    two = reconstruct(y, psf, devices=list(subdevices), lean=True, **kw)
    assert all(p["lean"] and not p["streamed"] for p in two.info["layout"]) and len(two.info["layout"]) == 2
    close(two.volume, whole.volume, np.float32)


def test_halos_matter(rt, subdevices, monkeypatch):
    """The comparisons above can fail: with the halo planes copied across the device border replaced by
    zeros (TV cut there), the two-device result differs from the whole solve far beyond rounding."""
    from cm2cl.solver.parts import Part

    psf, y, kw = problem()
    whole = reconstruct(y, psf, device=rt, **kw)
    real = Part.load_halo
    monkeypatch.setattr(Part, "load_halo", lambda self, which, plane: real(self, which, np.zeros_like(plane)))
    cut = reconstruct(y, psf, devices=list(subdevices), **kw)
    err = np.linalg.norm(cut.volume - whole.volume) / np.linalg.norm(whole.volume)
    assert err > 1e-3, err


def test_planner_fits_the_memory_it_is_given(rt):
    nz, P = 40, (640, 800)
    est = memory_estimate(nz, P, np.float32, "cl")
    whole = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=est["total"] + 1)
    assert len(whole) == 1 and not whole[0].streamed
    cap = est["total"] // 4
    vols = memory_estimate(1, P, np.float32, "cl")["volumes_per_plane"]
    streamed = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=cap)
    assert streamed[0].overlap is (rt.caps.kind != "CPU")       # 'auto': double-buffered on GPUs only
    lp = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=cap, overlap=True)[0]
    assert lp.streamed and lp.overlap and lp.device_bytes <= cap
    assert lp.device_bytes + est["per_plane"] + vols > cap       # the largest double-buffered slab that fits
    assert lp.host_bytes == nz * vols                            # the volumes, once, in host memory
    one = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=cap, overlap=False)[0]
    assert not one.overlap and one.slab_planes > lp.slab_planes and one.device_bytes + est["per_plane"] > cap
    # a cap that holds one plane's buffers but not two: one buffer set, no overlap
    tight = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=est["fixed"] + est["per_plane"] + vols // 2,
                        overlap=True)[0]
    assert tight.streamed and not tight.overlap and tight.slab_planes == 1
    two = plan_layout(nz, P, np.float32, "cl", [rt, rt], max_memory=est["total"] // 2 + est["fixed"])
    assert [(p.z0, p.z1, p.streamed) for p in two] == [(0, 20, False), (20, 40, False)]
    with pytest.raises(DeviceError, match="too large even streamed"):
        plan_layout(nz, P, np.float32, "cl", [rt], max_memory=est["fixed"])


def test_planner_goes_lean_before_it_streams(rt):
    """Between what the lean state and the whole state need, the planner keeps the planes resident and
    lean (7 real volumes and the PSF spectra per plane, one slab of x spectra); below it, it streams;
    ``lean`` forces or forbids it."""
    nz, P = 40, (640, 800)
    est = memory_estimate(nz, P, np.float32, "cl")
    slab = memory.LEAN_SLAB_PLANES
    lean_est = memory_estimate(nz, P, np.float32, "cl", lean_slab=slab)
    item = 4
    real, spec = P[0] * P[1] * item, P[0] * (P[1] // 2 + 1) * 2 * item
    assert est["per_plane"] - lean_est["per_plane"] == spec                  # one spectrum plane less per plane
    assert lean_est["volumes_per_plane"] == 7 * real + spec                  # 7 real volumes + the PSF spectra
    assert lean_est["fixed"] - est["fixed"] == slab * spec + real            # one slab of spectra, r_next
    cap = (est["total"] + lean_est["total"]) // 2
    (lp,) = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=cap)
    assert lp.lean and not lp.streamed and lp.slab_planes == slab and lp.device_bytes == lean_est["total"] <= cap
    (lp,) = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=cap, lean=False)
    assert lp.streamed and not lp.lean
    (lp,) = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=lean_est["total"] - 1)
    assert lp.streamed and not lp.lean
    (lp,) = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=est["total"] + 1)
    assert not lp.lean and not lp.streamed
    (lp,) = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=est["total"] + 1, lean=True)
    assert lp.lean and lp.device_bytes == lean_est["total"]
    (lp,) = plan_layout(nz, P, np.float32, "cl", [rt], max_memory=est["total"] + 1, lean=True, max_slab_planes=1)
    assert lp.lean and lp.slab_planes == 1
    from cm2cl.solver.memory import size_text
    # sizes in the unit that gives them three digits (a few KiB said 0.00 GiB)
    assert size_text(3 * 2**30) == "3 GiB" and size_text(1536 * 2**10) == "1.5 MiB" and size_text(700) == "700 bytes"
    with pytest.raises(DeviceError, match=f"need {size_text(lean_est['total'])} per device"):
        plan_layout(nz, P, np.float32, "cl", [rt], max_memory=lean_est["total"] - 1, stream=False)
    with pytest.raises(ValueError, match="lean: expected"):
        plan_layout(nz, P, np.float32, "cl", [rt], lean="yes")
    with pytest.raises(InputError, match="lean and stream: .* ask for one of them"):
        plan_layout(nz, P, np.float32, "cl", [rt], lean=True, stream=True)


def test_cli_streams_under_a_memory_cap_and_plans_it(rt, tmp_path, capsys):
    """`--max-memory` below the whole solve: the dry run shows streamed slabs and the traffic, the run
    streams them and writes the same volume as the run that keeps them on the device; a cap that holds
    not even one streamed plane is refused before any work, as is a --host-memory too small."""
    import tifffile

    from cm2cl import io
    from cm2cl.cli import main

    psf, y, _ = problem()
    tifffile.imwrite(tmp_path / "psf.tif", psf, photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", y)
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--max-iter", "15", "--quiet"]
    from cm2cl.solver.params import ADMMParams
    from cm2cl.solver.terms import state_counts, terms_for

    est = memory_estimate(7, (64, 80), np.float32, "cl", **state_counts(terms_for(ADMMParams())))   # no TV
    dbl = rt.caps.kind != "CPU"      # double-buffered slabs on GPUs, one buffer set on CPUs
    cap = str(est["fixed"] + 3 * (est["per_plane"] + dbl * est["volumes_per_plane"]))
    assert main(base + ["-o", str(tmp_path / "a.ome.tif"), "--max-memory", cap, "--dry-run"]) == 0
    text = capsys.readouterr().out
    suffix = " (double-buffered)" if dbl else ""
    assert f"planes 0..6, streamed in slabs of 3 planes{suffix}" in text
    moved = streamed_bytes_per_iteration(7, (64, 80), np.float32, "cl", None)
    assert f"moved between host and devices per iteration: {moved / 2**30:.2f} GiB" in text
    assert "s per iteration" in text and "host <-> device" in text
    assert main(base + ["-o", str(tmp_path / "a.ome.tif"), "--max-memory", cap]) == 0
    text = capsys.readouterr().out
    assert f"streamed in slabs of 3{suffix}" in text and "GB moved between host and devices" in text and "peak host RSS" in text
    assert main(base + ["-o", str(tmp_path / "b.ome.tif")]) == 0
    a, b = io.read_tiff(tmp_path / "a.ome.tif")[0], io.read_tiff(tmp_path / "b.ome.tif")[0]
    np.testing.assert_array_equal(a, b)
    capsys.readouterr()
    assert main(base + ["-o", str(tmp_path / "c.ome.tif"), "--max-memory", str(est["fixed"])]) == 2
    assert "too large even streamed" in capsys.readouterr().err
    assert main(base + ["-o", str(tmp_path / "c.ome.tif"), "--max-memory", cap, "--stream", "never"]) == 2
    assert "too large to keep on the device" in capsys.readouterr().err
    # between the lean and the whole state's needs: resident and lean, the same volume
    lean = memory_estimate(7, (64, 80), np.float32, "cl", lean_slab=2, **state_counts(terms_for(ADMMParams())))
    lean_cap = str((est["total"] + lean["total"]) // 2)
    assert main(base + ["-o", str(tmp_path / "d.ome.tif"), "--max-memory", lean_cap, "--dry-run"]) == 0
    assert "planes 0..6, resident, lean (x spectra in slabs of 2 planes)" in capsys.readouterr().out
    assert main(base + ["-o", str(tmp_path / "d.ome.tif"), "--max-memory", lean_cap]) == 0
    assert "resident, lean (x spectra in slabs of 2)" in capsys.readouterr().out
    np.testing.assert_allclose(io.read_tiff(tmp_path / "d.ome.tif")[0], b, rtol=0, atol=1e-5 * b.max())
    assert main(base + ["-o", str(tmp_path / "c.ome.tif"), "--max-memory", lean_cap, "--lean", "never",
                        "--dry-run"]) == 0
    assert "streamed in slabs" in capsys.readouterr().out
    assert main(base + ["-o", str(tmp_path / "c.ome.tif"), "--lean", "always", "--stream", "always"]) == 2
    assert "ask for one of them" in capsys.readouterr().err
    assert main(base + ["-o", str(tmp_path / "c.ome.tif"), "--host-memory", "1K"]) == 2
    assert "MiB allowed (--host-memory)" in capsys.readouterr().err
    assert not (tmp_path / "c.ome.tif").exists()


def test_pinned_host_copies_stream_the_same(rt, monkeypatch):
    """The pinned host copies a GPU streams from (buffers the driver allocates in host memory, mapped):
    forced on this CPU device, the double-buffered solve is bit-identical to the plain-memory one."""
    from cm2cl.solver.admm import ADMMSolver
    from cm2cl.solver.params import ADMMParams
    from cm2cl.solver.parts import Part

    psf, y, kw = problem()
    prm = ADMMParams(max_iter=kw["max_iter"], tol=0, tv_axial_weight=kw["tv_axial_weight"])
    plain = ADMMSolver(psf, prm, device=rt, padded_shape=kw["padded_shape"], stream=True, max_slab_planes=2)
    a = plain.solve(y)
    assert not plain.parts[0]._pinned
    real = Part.__init__
    monkeypatch.setattr(Part, "__init__", lambda self, *ar, **k: real(self, *ar, **{**k, "pinned": True}))
    pinned = ADMMSolver(psf, prm, device=rt, padded_shape=kw["padded_shape"], stream=True, max_slab_planes=2)
    assert len(pinned.parts[0]._pinned) == (3 + 2) * 4    # every volume's four slabs (3 real without TV, 2 complex)
    b = pinned.solve(y)
    assert np.array_equal(a.volume, b.volume)


def test_planes_are_shared_in_proportion_to_the_budgets():
    """The planner's split of nz planes over devices: contiguous runs covering 0..nz in proportion to the
    budgets, empty for a device without one, equal parts where no device has any (not NaN runs)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert memory._proportional_runs(12, [3, 1]) == [(0, 9), (9, 12)]
        assert memory._proportional_runs(10, [5, 0, 5]) == [(0, 5), (5, 5), (5, 10)]
        assert memory._proportional_runs(9, [0, 0, 0]) == [(0, 3), (3, 6), (6, 9)]
        assert memory._proportional_runs(7, [0]) == [(0, 7)]


def test_a_cpu_devices_budget_is_the_hosts_available_memory(rt, monkeypatch):
    """A CPU device's buffers are host memory, whatever its driver reports (PoCL: a quarter of the RAM on
    one machine, 94% on another): the planner's budget is 90% of what the host has available less the
    result it will hold and the runtime's share; a GPU's is 90% of its own memory; a cap lowers either."""
    import cm2cl.device as device
    from cm2cl.solver import memory

    monkeypatch.setattr(memory, "host_available_bytes", lambda: 20 * 2**30)
    cpu = device.Capabilities(**{**rt.caps.__dict__, "kind": "CPU", "global_mem": 6 * 2**30})
    monkeypatch.setattr(rt, "caps", cpu)
    want = int(0.9 * (20 * 2**30 - 3 * 2**30 - memory.CPU_RUNTIME_BYTES))
    assert memory.device_budget(rt, reserve=3 * 2**30) == want
    assert memory.device_budget(rt, max_memory=2**30, reserve=3 * 2**30) == 2**30
    monkeypatch.setattr(memory, "host_available_bytes", lambda: 2**29)   # less than the reserve: nothing
    assert memory.device_budget(rt, reserve=3 * 2**30) == 0
    gpu = device.Capabilities(**{**rt.caps.__dict__, "kind": "GPU", "global_mem": 6 * 2**30})
    monkeypatch.setattr(rt, "caps", gpu)
    assert memory.device_budget(rt, reserve=3 * 2**30) == int(0.9 * 6 * 2**30)


def test_cli_header_check_leaves_support_padding_to_the_solver(rt, tmp_path, capsys):
    """The header check plans the full padded grid, but `--padding support` pads to the PSF's support, known
    only once the stack is decoded: there the headers bound the grid by the sensor, and the solver plans the
    real one. A problem that streams on the full grid (refused under a tight --host-memory) but fits
    resident on its support's grid runs with --padding support (it was refused from the headers: the full
    frame of docs/fullframe.md, 29.6 GB planned on the full grid where 20.2 GB were used)."""
    import tifffile

    from cm2cl.cli import main
    from cm2cl.cli.plan import _decoded_bytes
    from cm2cl.solver.forward import choose_padded_shape, support_padding
    from cm2cl.solver.params import ADMMParams
    from cm2cl.solver.terms import state_counts, terms_for

    rng = np.random.default_rng(3)
    nz, M = 5, (48, 64)
    psf = np.zeros((nz,) + M, np.float32)
    for z in range(nz):                      # a compact stack: a few foci within 9 x 9 px of the axis
        for _ in range(3):
            psf[z, M[0] // 2 + rng.integers(-4, 5), M[1] // 2 + rng.integers(-4, 5)] += 1.0
    x = np.zeros((nz,) + M)
    x[1, 20, 30] = x[3, 10, 12] = 1.0
    y = sum(np.real(np.fft.ifft2(np.fft.fft2(np.fft.ifftshift(psf[z])) * np.fft.fft2(x[z]))) for z in range(nz))
    y = (y + 0.01).astype(np.float32)
    tifffile.imwrite(tmp_path / "psf.tif", psf, photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", y)
    counts = state_counts(terms_for(ADMMParams()))
    full = memory_estimate(nz, choose_padded_shape(M, "cl"), np.float32, "cl", **counts)
    sup = memory_estimate(nz, support_padding(psf, "cl")[1], np.float32, "cl", **counts)
    assert sup["total"] < 0.6 * full["total"]
    cap = (sup["total"] + full["total"]) // 2          # the full grid streams, the support's stays resident
    host = _decoded_bytes(y.shape, psf.shape) + 1024   # room to decode, none for streamed slabs
    base = ["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "--max-iter", "20",
            "--quiet", "--backend", "cl", "--lean", "never", "--max-memory", str(cap), "--host-memory", str(host)]
    assert main(base + ["-o", str(tmp_path / "a.ome.tif")]) == 2
    assert "holding the streamed slabs" in capsys.readouterr().err
    assert not (tmp_path / "a.ome.tif").exists()
    assert main(base + ["-o", str(tmp_path / "b.ome.tif"), "--padding", "support"]) == 0
    assert (tmp_path / "b.ome.tif").exists()
