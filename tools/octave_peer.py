"""The CM2 authors' ADMM solver (MATLAB, run under GNU Octave) beside cm2cl on the same problem: the real
DiffuserCam 3D data, the same normalised y and PSF stack, the same weights (cm2cl's defaults), the
same padded grid (2M, the authors' fixed choice). Each volume's objective and data residual are
evaluated by one float64 function (cm2cl.reference), against a long float64 cm2cl run of the problem.
Writes docs/octave_peer.md and docs/img/octave_peer_*.png.

    apt-get install octave      # octave-cli on PATH
    python tools/octave_peer.py --cm2-repo PATH [--bin 2] [--iters 200] [--long-iters 1500]

PATH: a checkout of github.com/bu-cisl/Computational-Miniature-Mesoscope-CM2 (the solver is
Algorithm/model_based_3D_deconvolution_CM2_V1/utilities/ADMM_LSI_deconv_3D.m). A folder of the git
repository without a work tree (a mirror) works too: the file is read with ``git show``.

How the authors' model maps onto cm2cl's: both are circular convolution on the padded grid, cropped
to the sensor window centred on it, with the PSF's origin at (My//2, Mx//2), so the lateral grids
agree pixel for pixel when cm2cl is given ``padded_shape = 2M``. The authors convolve in 3D (an FFT
along depth too) and read the measurement off one plane, so their volume's plane k pairs with PSF
plane nz-1-k: the PSF stack is handed to Octave reversed in depth, and the volume comes back in
cm2cl's order (checked below: the data residual of the other order is printed and must be worse).
Shims (Octave lacks them without its image and wavelet packages): ``wthresh`` (soft threshold),
``padarray`` (zeros on both sides), two-argument ``round``; ``write_mat_to_tif`` is a no-op (the tool
saves the volume itself).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import datasets  # noqa: E402
import cm2cl  # noqa: E402
from cm2cl import analysis, reference  # noqa: E402
from cm2cl.reference.admm import normalisation  # noqa: E402
from cm2cl.reference.tv import tv_value  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"
SOLVER = "Algorithm/model_based_3D_deconvolution_CM2_V1/utilities/ADMM_LSI_deconv_3D.m"

SHIMS = {
    "wthresh.m": "function y = wthresh(x, kind, t)\n  y = sign(x) .* max(abs(x) - t, 0);\nend\n",
    "padarray.m": ("function y = padarray(x, p)\n  p(end+1:ndims(x)) = 0;\n  sz = size(x); sz(end+1:numel(p)) = 1;\n"
                   "  y = zeros(sz + 2 * p(1:numel(sz)), class(x));\n  idx = arrayfun(@(k) p(k) + (1:sz(k)), "
                   "1:numel(sz), 'UniformOutput', false);\n  y(idx{:}) = x;\nend\n"),
    "round.m": ("function y = round(x, n)\n  if nargin < 2\n    y = builtin('round', x);\n  else\n"
                "    y = builtin('round', x * 10^n) / 10^n;\n  end\nend\n"),
    "write_mat_to_tif.m": "function write_mat_to_tif(varargin)\nend\n",
}

DRIVER = """
addpath('{util}'); addpath('{shim}');
load('{inp}');
para = struct('mu1', 1, 'mu2', 1, 'mu3', 1, 'mu4', 1, 'clip_min', 0, 'clip_max', 1e30, 'color', 0, ...
  'tau_l1', tau_l1, 'tau_tv', tau_tv, 'rtol', 1.5, 'mu_ratio', 1.1, 'display_flag', 0, ...
  'termination_ratio', termination_ratio, 'plateau_tolerence', 4, 'maxiter', maxiter, ...
  'img_save_period', 1e9, 'img_save_path', '');
t0 = tic; x = ADMM_LSI_deconv_3D(y, psf, para); seconds = toc(t0);
save('-v7', '{out}', 'x', 'seconds');
"""


def solver_source(repo: Path) -> str:
    f = repo / SOLVER
    if f.is_file():
        return f.read_text()
    out = subprocess.run(["git", "-C", str(repo), "show", f"HEAD:{SOLVER}"], capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"--cm2-repo {repo}: {SOLVER} not found ({out.stderr.strip()})")
    return out.stdout


def evaluate(psf_n, y_n, x, l1, tv, P):
    """(objective, data residual ||CHx - y|| / ||y||) of max(x, 0) on the normalised problem, float64."""
    x = np.maximum(np.asarray(x, np.float64), 0.0)
    r = reference.forward(psf_n, x, P) - y_n
    obj = 0.5 * float((r ** 2).sum()) + l1 * float(x.sum()) + tv * tv_value(x)
    return obj, float(np.linalg.norm(r) / np.linalg.norm(y_n))


def even_smooth(m: int) -> int:
    """The largest even size <= m whose double has no prime factor above 7."""
    def smooth(n):
        for f in (2, 3, 5, 7):
            while n % f == 0:
                n //= f
        return n == 1
    return next(k for k in range(m - m % 2, 0, -2) if smooth(2 * k))


def normalised(rec) -> np.ndarray:
    """A cm2cl result's volume on the problem the solver saw (it scales the volume back by
    psf_scale / y_scale, which is ~1 here: the data come in normalised)."""
    return rec.volume_padded * (rec.scaling["y_scale"] / rec.scaling["psf_scale"])


def run_octave(repo, psf_n, y_n, l1, tv, iters, termination_ratio, work: Path):
    import scipy.io

    util = work / "util"
    shim = work / "shim"
    util.mkdir()
    shim.mkdir()
    (util / "ADMM_LSI_deconv_3D.m").write_text(solver_source(repo))
    for name, text in SHIMS.items():
        (shim / name).write_text(text)
    # Octave's (rows, cols, layers), PSF reversed in depth (see the module's docstring)
    scipy.io.savemat(work / "in.mat", {"y": y_n.astype(np.float32), "tau_l1": l1, "tau_tv": tv,
                                       "psf": np.ascontiguousarray(psf_n[::-1].transpose(1, 2, 0), np.float32),
                                       "maxiter": float(iters), "termination_ratio": termination_ratio})
    (work / "cm2_peer_run.m").write_text(DRIVER.format(util=util, shim=shim, inp=work / "in.mat", out=work / "out.mat"))
    t = time.perf_counter()
    proc = subprocess.run(["octave-cli", "--no-gui", "--quiet", str(work / "cm2_peer_run.m")], capture_output=True,
                          text=True, cwd=work)
    wall = time.perf_counter() - t
    if proc.returncode:
        raise SystemExit(f"octave-cli failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    out = scipy.io.loadmat(work / "out.mat")
    its = [int(m) for m in re.findall(r"iteration: (\d+),", proc.stdout)]
    stop = "rule (evolution ratio)" if "terminating" in proc.stdout else "max_iter"
    return out["x"].transpose(2, 0, 1).astype(np.float64), float(np.ravel(out["seconds"])[0]), wall, max(its), stop


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cm2-repo", type=Path, required=True, help="checkout (or mirror) of the CM2 authors' repository")
    ap.add_argument("--bin", type=int, default=2)
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--long-iters", type=int, default=1500)
    ap.add_argument("--termination-ratio", default="0.01,0",
                    help="comma list, one run of the authors' solver each: its stopping rule's relative change "
                         "per iteration (their default 0.01; 0 runs all --iters)")
    args = ap.parse_args(argv)
    if shutil.which("octave-cli") is None:
        raise SystemExit("octave-cli not found: apt-get install octave")
    solver_source(args.cm2_repo)   # fail before the long work

    psf, y = datasets.diffusercam_3d(args.bin)
    if psf.shape[0] % 2:
        raise SystemExit(f"the authors' solver needs an even number of planes, not {psf.shape[0]}")
    # ... and even sensor sides, and the 2M grid must suit every FFT backend (7-smooth): each side is cut
    # to the largest such size (the same cut for both solvers)
    y = y[: even_smooth(y.shape[0]), : even_smooth(y.shape[1])]
    psf = psf[:, : y.shape[0], : y.shape[1]]
    P = (2 * y.shape[0], 2 * y.shape[1])
    ps, ys = normalisation(psf, y, P)
    psf_n, y_n = psf * ps, y * ys

    t = time.perf_counter()
    d = cm2cl.reconstruct(y_n, psf_n, padded_shape=P, max_iter=args.iters, psf_refine=0)
    td = time.perf_counter() - t
    l1, tv = d.info["l1"], d.info["tv"]
    t = time.perf_counter()
    L = cm2cl.reconstruct(y_n, psf_n, padded_shape=P, dtype=np.float64, max_iter=args.long_iters, tol=0,
                          l1=l1, tv=tv, psf_refine=0)
    tl = time.perf_counter() - t
    obj_L, res_L = evaluate(psf_n, y_n, normalised(L), l1, tv, P)
    obj_d, res_d = evaluate(psf_n, y_n, normalised(d), l1, tv, P)
    rows = [("cm2cl defaults (float32, adaptive penalties)", d.iterations, d.info.get("stop", ""), td, obj_d, res_d)]
    checks = []
    for ratio in [float(r) for r in args.termination_ratio.split(",")]:
        with tempfile.TemporaryDirectory() as tmp:
            xo, so, wo, it_o, stop_o = run_octave(args.cm2_repo, psf_n, y_n, l1, tv, args.iters, ratio, Path(tmp))
        obj_o, res_o = evaluate(psf_n, y_n, xo, l1, tv, P)
        obj_flip, res_flip = evaluate(psf_n, y_n, xo[::-1], l1, tv, P)
        print(f"authors' volume, data residual in cm2cl's depth order {res_o:.4f}, reversed {res_flip:.4f}")
        if res_flip < res_o:
            raise SystemExit("the authors' volume fits better in reversed depth order: the mapping is wrong")
        checks.append((ratio, res_o, res_flip))
        rows.append((f"CM2 authors' ADMM (Octave, single, mu 1, x1.1 balancing, stop ratio {ratio:g})", it_o, stop_o,
                     so, obj_o, res_o))
    rows.append((f"cm2cl long float64 ({args.long_iters} iterations, tol 0)", L.iterations, L.info.get("stop", ""),
                 tl, obj_L, res_L))
    gap = lambda o: (o - obj_L) / abs(obj_L)  # noqa: E731
    (DOCS / "img").mkdir(parents=True, exist_ok=True)
    crop = d.crop
    analysis.mip_png(xo[(slice(None),) + tuple(crop)].clip(0), DOCS / "img" / "octave_peer_authors_mip.png",
                     title=f"DiffuserCam 3D: the CM2 authors' ADMM (Octave, {it_o} iterations)", gamma=0.6)
    analysis.mip_png(d.volume, DOCS / "img" / "octave_peer_cm2cl_mip.png",
                     title="DiffuserCam 3D: cm2cl defaults, same problem", gamma=0.6)
    from cm2cl.device import get_runtime

    lines = ["# The CM2 authors' solver beside cm2cl", "",
             f"Made by `python tools/octave_peer.py --cm2-repo PATH --bin {args.bin} --iters {args.iters} "
             f"--long-iters {args.long_iters}` with {_octave_version()} and cm2cl on "
             f"{get_runtime().caps.implementation}, 2 CPU cores (one run). The problem: DiffuserCam 3D "
             f"({psf.shape[0]} planes, sensor {y.shape[0]} x {y.shape[1]} after {args.bin}x binning, each side cut to the largest even size whose double is 7-smooth), normalised "
             f"(max y = 1, ||H|| = 1 on the {P[0]} x {P[1]} grid), weights l1 = {l1:.3g}, tv = {tv:.3g} "
             "(cm2cl's defaults) for both solvers, the authors' fixed 2M padding for both. Objective "
             "1/2 ||CHx - y||^2 + l1 ||x||_1 + tv TV(x) and data residual ||CHx - y|| / ||y|| are evaluated in "
             "float64 by cm2cl.reference on max(x, 0) of each volume; the gap is relative to the long run.",
             "", "The authors' solver runs as they ship it (`cm2_related_code.m`: mu1..mu4 = 1, residual "
             "balancing by x1.1 when residuals differ by 1.5x, stop when the relative change stays under "
             "the stop ratio (theirs: 0.01) for 4 iterations without a penalty change; 0 never stops), up to "
             f"{args.iters} iterations (its loop runs one more); its seconds are its own loop's (tic/toc), on the "
             "same 2 cores.", "",
             "| solver | iterations | stop | s | objective | gap to the long run | data residual |",
             "|---|---|---|---|---|---|---|"]
    for name, it, stop, s, obj, res in rows:
        lines.append(f"| {name} | {it} | {stop} | {s:.0f} | {obj:.6g} | {gap(obj):.2e} | {res:.4f} |")
    lines += ["", "Depth order check: the authors' volume, taken in cm2cl's order, fits the data with residual "
              + "; ".join(f"{a:.4f} against {b:.4f} reversed (stop ratio {r:g})" for r, a, b in checks) + ".", "",
              "The data carry no physical scale: the MIP axes read um but are pixels and plane indices.", "",
              "![authors](img/octave_peer_authors_mip.png)", "", "![cm2cl](img/octave_peer_cm2cl_mip.png)", ""]
    (DOCS / "octave_peer.md").write_text("\n".join(lines))
    print("\n".join(lines))


def _octave_version() -> str:
    out = subprocess.run(["octave-cli", "--version"], capture_output=True, text=True).stdout
    return out.splitlines()[0].strip() if out else "GNU Octave"


if __name__ == "__main__":
    main()
