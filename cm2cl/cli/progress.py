"""Progress bars on stderr: one tqdm bar, off with ``--quiet`` and when stderr is not a terminal (logs,
pipes, batch jobs), where the summary line and the log files say how the run went."""

from __future__ import annotations

import sys


def _bar(total: int, quiet: bool, stream, desc: str, unit: str):
    stream = sys.stderr if stream is None else stream
    if quiet or not stream.isatty() or not total:
        return None
    from tqdm import tqdm

    return tqdm(total=total, file=stream, desc=desc, unit=unit, dynamic_ncols=True)


class Progress:
    """ADMM iterations, with objective and primal / dual residuals as the postfix; call it with each log row."""

    def __init__(self, total: int, quiet: bool, stream=None):
        self.bar = _bar(total, quiet, stream, "ADMM", "it")

    def __call__(self, row):
        if self.bar is None:
            return
        self.bar.set_postfix(obj=f"{row['objective']:.4e}", primal=f"{row['primal']:.2e}",
                             dual=f"{row['dual']:.2e}", refresh=False)
        self.bar.update(int(row["iter"]) - self.bar.n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


class FrameProgress(Progress):
    """Frames of a series; call it with (frame index, the frame's info)."""

    def __init__(self, total: int, quiet: bool, stream=None):
        self.bar = _bar(total, quiet, stream, "frames", "frame")

    def __call__(self, i, info):
        if self.bar is not None:
            self.bar.set_postfix(frame=i, it=info["iterations"], refresh=False)
            self.bar.update(1)
