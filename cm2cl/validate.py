"""The validation layer: array checks for the public functions, and :class:`Checker`, the one
mechanism that checks scene files, solver parameters and optics against specs. Each failure is an
InputError whose one-line message names the input (file or argument), the key path and the problem."""

from __future__ import annotations

import math

import numpy as np

from .errors import InputError


def real_array(a, name: str, ndims=(2, 3)) -> np.ndarray:
    """A finite floating-point numpy array with one of ``ndims`` dimensions."""
    if not isinstance(a, np.ndarray):
        try:
            a = np.asarray(a)
        except Exception as exc:  # noqa: BLE001 - anything numpy refuses
            raise InputError(f"{name}: not convertible to an array ({exc})") from exc
    if a.dtype.kind != "f":
        raise InputError(f"{name}: dtype {a.dtype} is not floating point (convert to float32/float64 "
                         "after subtracting the camera offset)")
    if a.ndim not in ndims:
        raise InputError(f"{name}: expected {' or '.join(f'{d}D' for d in ndims)} array, got shape {a.shape}")
    if a.size == 0:
        raise InputError(f"{name}: empty array of shape {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputError(f"{name}: contains {int(bad.sum())} NaN/Inf values (first at index {idx})")
    return a


def image_array(a, name: str, ndims=(2, 3)) -> np.ndarray:
    """Camera data as a float array: integer images (uint8, uint16, int32, ...) become float64, float
    arrays pass unchanged; booleans, complex and non-numeric data are refused."""
    a = np.asarray(a) if not isinstance(a, np.ndarray) else a
    if a.dtype.kind in "ui":
        return a.astype(np.float64)
    if a.dtype.kind != "f":
        raise InputError(f"{name}: dtype {a.dtype} is not a real number type (use float or integer camera data)")
    return a


def psf_stack(psf, name: str = "psf") -> np.ndarray:
    """PSF as (nz, My, Mx); 2D means one depth plane. Every plane must carry some light."""
    psf = real_array(psf, name)
    if psf.ndim == 2:
        psf = psf[None]
    energy = np.abs(psf).reshape(psf.shape[0], -1).sum(axis=1)
    zero = np.flatnonzero(energy == 0)
    if zero.size:
        raise InputError(f"{name}: depth plane(s) {zero.tolist()} are all zero")
    return psf


class Checker:
    """The one validation mechanism of cm2cl: values and tables of values checked against specs
    ({"type": "float"|"int"|"bool"|"str"|"vec2"|"vec3"|"intpair"|"points3", "min", "max", "exclusive",
    "choices", "words", "default", "required", "optional"}; "words": strings a number field also takes). Every failure is an InputError
    "<label>: <key path>: <problem>" (the label names the file or the call, e.g. "scene 'a.toml'")."""

    def __init__(self, label: str | None = None, prefix: str = ""):
        self.label = label
        self.prefix = prefix

    def fail(self, key, problem):
        key = f"{self.prefix}.{key}" if self.prefix and key else (key or self.prefix)
        head = f"{self.label}: " if self.label else ""
        raise InputError(f"{head}{key}: {problem}")

    def fields(self, obj, specs: dict):
        """Check attributes of a (dataclass) object against specs; returns the checked values."""
        return {name: self.value(name, getattr(obj, name), spec) for name, spec in specs.items()}

    def number(self, key, v, spec=None, integer=False):
        spec = spec or {}
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            self.fail(key, f"expected a {'whole ' if integer else ''}number, got {v!r}")
        if integer and not float(v).is_integer():
            self.fail(key, f"expected a whole number, got {v!r}")
        if not math.isfinite(v):
            self.fail(key, f"must be finite, got {v!r}")
        lo, hi, excl = spec.get("min"), spec.get("max"), spec.get("exclusive", False)
        if lo is not None and (v < lo or (excl and v == lo)):
            self.fail(key, f"must be {'>' if excl else '>='} {lo}, got {v!r}")
        if hi is not None and v > hi:
            self.fail(key, f"must be <= {hi}, got {v!r}")
        return int(v) if integer else float(v)

    def vector(self, key, v, n, spec=None, integer=False):
        if not isinstance(v, (list, tuple)) or len(v) != n:
            self.fail(key, f"expected a list of {n} numbers, got {v!r}")
        return [self.number(f"{key}[{i}]", t, spec, integer) for i, t in enumerate(v)]

    def value(self, key, v, spec):
        kind = spec["type"]
        if v is None:
            return None
        if isinstance(v, str) and v in spec.get("words", ()):   # e.g. psf_refine='auto'
            return v
        if kind == "float":
            return self.number(key, v, spec)
        if kind == "int":
            return self.number(key, v, spec, integer=True)
        if kind == "bool":
            if not isinstance(v, bool):
                self.fail(key, f"expected true or false, got {v!r}")
            return v
        if kind == "str":
            if not isinstance(v, str):
                self.fail(key, f"expected a string, got {v!r}")
            if "choices" in spec and v not in spec["choices"]:
                self.fail(key, f"unknown value {v!r} (known: {', '.join(spec['choices'])})")
            return v
        if kind == "vec2":
            return self.vector(key, v, 2, spec)
        if kind == "vec3":
            return self.vector(key, v, 3, spec)
        if kind == "intpair2":   # (rows, cols): two whole numbers, each within the spec's bounds
            return self.vector(key, v, 2, spec, integer=True)
        if kind == "intpair":
            out = self.vector(key, v, 2, spec, integer=True)
            if out[1] < out[0]:
                self.fail(key, f"expected [first, last] with first <= last, got {v!r}")
            return out
        if kind == "points3":
            if not isinstance(v, list) or not v:
                self.fail(key, f"expected a non-empty list of [x, y, z] positions, got {v!r}")
            return [self.vector(f"{key}[{i}]", p, 3) for i, p in enumerate(v)]
        raise AssertionError(kind)

    def named_tables(self, data, section, field, known, what):
        """Yield (index, key, table, name) for each table of the array ``section`` whose ``field``
        names one of ``known`` (objects by 'type', effects by 'name')."""
        items = data.get(section, [])
        if not isinstance(items, list):
            self.fail(section, f"expected an array of tables ([[{section}]])")
        for i, t in enumerate(items):
            key = f"{section}[{i}]"
            if not isinstance(t, dict):
                self.fail(key, f"expected a table, got {t!r}")
            if field not in t:
                self.fail(f"{key}.{field}", f"missing (known: {', '.join(known)})")
            name = t[field]
            if name not in known:
                self.fail(f"{key}.{field}", f"unknown {what} {name!r} (known: {', '.join(known)})")
            yield i, key, t, name

    def table(self, key, d, specs, skip=()):
        """Validate a parameter table against specs; returns it with defaults filled."""
        if not isinstance(d, dict):
            self.fail(key, f"expected a table, got {d!r}")
        unknown = [k for k in d if k not in specs and k not in skip]
        if unknown:
            self.fail(f"{key}.{unknown[0]}" if key else unknown[0],
                      f"unknown key (known: {', '.join(specs)})")
        out = {}
        for name, spec in specs.items():
            sub = f"{key}.{name}" if key else name
            if name in d:
                out[name] = self.value(sub, d[name], spec)
            elif spec.get("required"):
                self.fail(sub, "missing (required)")
            else:
                out[name] = spec.get("default")
        return out
