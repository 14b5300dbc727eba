"""Outputs that appear only when complete: output-folder checks, staged folders, JSON records."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["jsonable", "check_output_dir", "StagedOutput"]


def jsonable(obj):
    """Plain JSON types for numpy arrays and scalars, paths, tuples and dataclasses (recursively)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "__dataclass_fields__"):
        import dataclasses
        return jsonable(dataclasses.asdict(obj))
    return obj


def check_output_dir(outdir) -> Path:
    """The parent of an output folder, created if needed; an InputError if ``outdir`` is a file."""
    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise InputError(f"output '{out}': exists and is not a directory")
    parent = out.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"output '{out}': cannot create its parent directory ({exc})") from exc
    return parent


class StagedOutput:
    """Build a folder of outputs beside ``outdir`` and move it in only when complete.

    ``with StagedOutput(outdir) as stage:`` gives ``stage.dir`` (a temporary folder next to
    ``outdir``) to write into; ``stage.publish(names, record_name, text)`` then moves ``names`` into
    ``outdir`` and writes the JSON record ``record_name`` last, so an interrupted run never leaves a
    folder that looks complete. The temporary folder is removed in any case.
    """

    def __init__(self, outdir):
        import tempfile

        self.out = Path(outdir)
        parent = check_output_dir(self.out)
        self.dir = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.partial-", dir=parent))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(self.dir, 0o777 & ~umask)  # mkdtemp makes it private; the result is a normal folder

    def publish(self, names, record_name: str, text: str):
        out, tmp = self.out, self.dir
        if not out.exists():
            (tmp / record_name).write_text(text)
            os.replace(tmp, out)
            return
        stale = out / record_name
        if stale.exists():
            stale.unlink()  # the folder no longer looks complete while its files are replaced
        for n in names:
            if (out / n).is_dir():
                shutil.rmtree(out / n)
            os.replace(tmp / n, out / n)
        (out / f"{record_name}.partial").write_text(text)
        os.replace(out / f"{record_name}.partial", out / record_name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.dir.exists():
            shutil.rmtree(self.dir, ignore_errors=True)
        return False
