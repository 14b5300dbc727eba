"""tools/gpu_check.sh (issue 28): its paths on the device at hand (PoCL in CI) at a small size: every kernel
program builds, a row per FFT backend with a positive time per iteration, the section written."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_gpu_check_runs_its_paths_at_a_small_size(rt, tmp_path):
    from cm2cl.device import fft

    out = tmp_path / "gpu_check.md"
    r = subprocess.run(["bash", str(ROOT / "tools" / "gpu_check.sh"), "--size", "64x80x2", "--iters", "2",
                        "--no-tests", "--out", str(out)], cwd=tmp_path, capture_output=True, text=True,
                       timeout=600, env={**os.environ, "PYTHON": sys.executable})
    assert r.returncode == 0, r.stdout + r.stderr
    text = out.read_text()
    assert text.startswith("# GPU check") and f"## GPU check: {rt.caps.name}" in text
    rows = [ln for ln in text.splitlines() if ln.startswith("| 64 x 80 x 2 |")]
    backends = [b for b in ("cl", "vkfft") if b in fft.available_backends()]
    assert [ln.split(" | ")[1] for ln in rows] == backends
    assert all(float(ln.split(" | ")[4]) > 0 for ln in rows)
    n_cl = len([p for p in (ROOT / "kernels").iterdir() if p.suffix == ".cl" and p.name != "common.cl"])
    assert f"kernels built: {n_cl * (2 if rt.caps.fp64 else 1)} programs" in text
