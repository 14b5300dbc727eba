"""Progress on stderr: a tqdm bar on a terminal; elsewhere (batch logs, pipes, ``| tee``) one line every
``every`` seconds (``--progress-every``, default 30 s; 0: none) with the iteration or frame, the objective
and the time left at this rate; nothing with ``--quiet``. A bar is closed at the real count (a solve that
converges early ends at its last iteration, not at a partial bar)."""

from __future__ import annotations

import sys
import time

#: seconds between progress lines when stderr is not a terminal
DEFAULT_EVERY = 30.0


def _bar(total: int, stream, desc: str, unit: str):
    from tqdm import tqdm

    return tqdm(total=total, file=stream, desc=desc, unit=unit, dynamic_ncols=True)


def _duration(s: float) -> str:
    s = max(float(s), 0.0)
    return f"{s:.0f} s" if s < 120 else (f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.1f} h")


class _Reporter:
    """A bar (terminal) or timed lines (anything else) for ``total`` steps of ``unit``."""

    def __init__(self, total: int, quiet: bool, stream, desc: str, unit: str, every: float):
        self.stream = sys.stderr if stream is None else stream
        self.total, self.unit, self.every = int(total or 0), unit, float(every)
        self.bar = self.lines = None
        self.n, self.t0 = 0, time.perf_counter()
        self._last = self.t0
        if quiet or not self.total:
            return
        if self.stream.isatty():
            self.bar = _bar(self.total, self.stream, desc, unit)
        elif self.every > 0:
            self.lines = True

    def step(self, n: int, postfix: dict, words: str):
        """Advance to ``n`` done; ``postfix`` for the bar, ``words`` for a line."""
        self.n = n
        if self.bar is not None:
            self.bar.set_postfix(postfix, refresh=False)
            self.bar.update(n - self.bar.n)
        elif self.lines:
            now = time.perf_counter()
            if now - self._last >= self.every:
                self._last = now
                el = now - self.t0
                if n > self.total:   # past the estimate (psf_refine auto's rounds per lenslet are not in it)
                    print(f"cm2cl: {self.unit} {n}, past the {self.total} first estimated, {words}, "
                          f"{_duration(el)} so far", file=self.stream, flush=True)
                    return
                left = el / max(n, 1) * max(self.total - n, 0)
                print(f"cm2cl: {self.unit} {n}/{self.total}, {words}, {_duration(el)} so far, "
                      f"at most {_duration(left)} left at this rate", file=self.stream, flush=True)

    def close(self):
        if self.bar is not None:
            if self.bar.n < self.bar.total:      # stopped early (converged): the bar ends where the run did
                self.bar.total = self.bar.n
                self.bar.refresh()
            self.bar.close()
            self.bar = None


class Progress(_Reporter):
    """ADMM iterations, with objective and primal / dual residuals; call it with each log row (``iter``
    counts on across the rounds of a PSF refinement: ``total`` is all of them)."""

    def __init__(self, total: int, quiet: bool, stream=None, every: float = DEFAULT_EVERY):
        super().__init__(total, quiet, stream, "ADMM", "iteration", every)

    def __call__(self, row):
        self.step(int(row["iter"]), {"obj": f"{row['objective']:.4e}", "primal": f"{row['primal']:.2e}",
                                     "dual": f"{row['dual']:.2e}"},
                  f"objective {row['objective']:.4e}, residuals {row['primal']:.2e} / {row['dual']:.2e}")


class FrameProgress(_Reporter):
    """Frames of a series; call it with (frame index, the frame's info)."""

    def __init__(self, total: int, quiet: bool, stream=None, every: float = DEFAULT_EVERY):
        super().__init__(total, quiet, stream, "frames", "frame", every)

    def __call__(self, i, info):
        self.step(self.n + 1, {"frame": i, "it": info["iterations"]},
                  f"last frame {i}: {info['iterations']} iterations"
                  + (f", objective {info['objective']:.4e}" if info.get("objective") is not None else ""))
