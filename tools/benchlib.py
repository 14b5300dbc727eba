"""Shared helpers of the benchmarks: timing, the copy-bandwidth floor, writing docs/ tables."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parents[1] / "docs"


def best_time(fn, repeat=5, warmup=1, sync=None) -> float:
    """Best wall time of `repeat` calls (after `warmup`), synchronising with `sync()` if given."""
    for _ in range(warmup):
        fn()
    if sync:
        sync()
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        if sync:
            sync()
        best = min(best, time.perf_counter() - t)
    return best


def copy_bandwidth(rt, nbytes=256 * 2**20) -> float:
    """Bytes per second of a device copy kernel (read + write counted), float32."""
    from cm2cl.device.rates import copy_rate

    return copy_rate(rt, nbytes)


def parse_size(spec: str):
    """'324x432x16' -> (My, Mx, nz): sensor rows, columns and depth planes."""
    my, mx, nz = (int(v) for v in spec.split("x"))
    return my, mx, nz


def markdown_table(head, rows) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def write_section(name: str, text: str, path: Path = DOCS / "benchmarks.md") -> Path:
    """Replace (or append) the section `## name` of docs/benchmarks.md with `text`."""
    path.parent.mkdir(exist_ok=True)
    doc = path.read_text() if path.exists() else "# Benchmarks\n\nEvery table here is written by a script in `tools/`; re-run it to refresh.\n"
    block = f"## {name}\n\n{text.strip()}\n"
    pat = re.compile(rf"^## {re.escape(name)}\n.*?(?=^## |\Z)", re.S | re.M)
    doc = pat.sub(lambda m: block + "\n", doc) if pat.search(doc) else doc.rstrip() + "\n\n" + block
    path.write_text(doc)
    return path


def made_by(tool: str, argv, seconds: float, doc: str) -> str:
    """A generated page's first paragraph: the command (``python tools/TOOL`` and its non-default ``argv``), the
    minutes it took, the OpenCL device and machine, and the third paragraph of the tool's ``doc`` (what it does)."""
    import platform

    from cm2cl.device.runtime import get_runtime

    rt = get_runtime(None)
    return (f"Made by `python tools/{tool}{' ' + ' '.join(argv) if argv else ''}` in {seconds / 60:.1f} min on "
            f"{rt.caps.platform} ({rt.caps.name}), {platform.machine()}, one run. "
            + doc.split("\n\n")[2].replace("\n", " "))


def refine_words(info) -> str:
    """What the PSF refinement did (``rec.info['psf_refine']``), for a table: its mode and rounds ('auto, 2
    rounds': the common kernel only), and where 'auto' solved both answers, which one it kept."""
    if not info:
        return "-"
    n = info.get("rounds")
    out = f"{info.get('mode', '-')}, {n} round{'s' if n != 1 else ''}" if n is not None else str(info.get("mode", "-"))
    cmp = info.get("compared")
    if cmp:
        out += f" ({'kernels per lenslet' if cmp['kept'] == 'lenslets' else 'common kernel'} kept of both)"
    return out


def with_hand_written(text: str, path: Path) -> str:
    """``text`` (a tool's generated markdown) followed by the hand-written part of the page at ``path``, kept
    across re-runs: everything from its first "## " heading that says "(hand-written"."""
    if not path.exists():
        return text
    old = path.read_text()
    m = re.search(r"^## [^\n]*\(hand-written", old, re.M)
    return text + "\n" + old[m.start():] if m else text


def residual(psf, y, rec) -> float:
    """||C H x - y|| / ||y|| in float64 with the PSF the final solve used (the given one, or the refined one
    ``rec.psf`` after a PSF refinement), plus the reconstruction's own 2D background estimate,
    ``rec.background``, where it has one."""
    from cm2cl import reference

    h = rec.psf if getattr(rec, "psf", None) is not None else psf
    yh = reference.forward(h, rec.volume_padded, rec.volume_padded.shape[1:])
    b = getattr(rec, "background", None)
    if isinstance(b, np.ndarray) and b.shape == yh.shape:
        yh = yh + b
    return float(np.linalg.norm(yh - y) / np.linalg.norm(y))
