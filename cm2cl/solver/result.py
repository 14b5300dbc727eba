"""The result of a reconstruction: the volume, the scaling applied, and the iteration log."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

LOG_FIELDS = ("iter", "objective", "data", "l1", "tv", "rel_change", "primal", "dual",
              "r_v", "s_v", "r_u", "s_u", "r_w", "s_w", "mu_v", "mu_u", "mu_w", "seconds")


@dataclass
class Reconstruction:
    """A reconstructed volume in the measurement's intensity units.

    ``volume_padded`` is the (nz, Py, Px) object on the padded grid (it includes the emitters
    outside the field of view that the unknown-boundary model recovers); ``volume`` is its
    (nz, My, Mx) part on the sensor field of view.  ``log`` has one dict per iteration with the
    fields of ``LOG_FIELDS``: objective terms and residuals are those of the normalised problem.
    ``scaling`` records the normalisation: the solver saw y * y_scale and PSFs * psf_scale, and
    the volume was multiplied back by psf_scale / y_scale.
    """

    volume_padded: np.ndarray
    crop: tuple
    log: list = field(default_factory=list)
    scaling: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    #: object-space voxel size (dz, dy, dx) in um of ``volume``, when known (from the PSF stack)
    voxel_size_um: tuple | None = None
    #: depth of each plane in um, when known
    depths_um: np.ndarray | None = None
    #: the background b of the model y = C H x + b on the sensor (My, Mx), in the measurement's units, when
    #: the data term has one (``background='model'``)
    background: np.ndarray | None = None
    #: the PSF stack the final solve used, when it was self-calibrated (``psf_refine``), in the given PSF's units
    psf: np.ndarray | None = None

    @property
    def volume(self) -> np.ndarray:
        return self.volume_padded[(slice(None),) + tuple(self.crop)]

    @property
    def iterations(self) -> int:
        return len(self.log)

    @property
    def seconds(self) -> float:
        return float(self.log[-1]["seconds"]) if self.log else 0.0

    @property
    def history(self) -> dict:
        """The iteration log as arrays, one per field of ``LOG_FIELDS`` (like SCICO's itstat)."""
        return {k: self.log_array(k) for k in LOG_FIELDS}

    def log_array(self, name: str) -> np.ndarray:
        return np.array([row[name] for row in self.log], dtype=float)

    def write_log(self, path, fmt: str | None = None, extra: dict | None = None) -> Path:
        """Write the iteration log as CSV (``fmt='csv'``, or a ``.csv`` path) or JSON (with the metadata,
        and ``extra`` keys at the top)."""
        path = Path(path)
        if (fmt or ("csv" if path.suffix.lower() == ".csv" else "json")) == "csv":
            with path.open("w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=LOG_FIELDS)
                w.writeheader()
                for row in self.log:
                    w.writerow({k: row[k] for k in LOG_FIELDS})
        else:
            doc = {**(extra or {}), "params": self.params, "scaling": self.scaling, "info": self.info,
                   "log": self.log}
            path.write_text(json.dumps(doc, indent=1, default=float))
        return path
