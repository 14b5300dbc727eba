"""``cm2cl verify STORE``: check every frame marked done in a series' OME-Zarr store against the SHA-256
recorded when it was written (a chunk deleted or overwritten is found); exit 0 when all match, 1 when some do
not (rerunning the job's command computes those again), 2 when STORE is not a cm2cl store."""

from __future__ import annotations

import sys

__all__ = ["register", "command"]


def register(sub):
    v = sub.add_parser("verify", help="check a series' OME-Zarr store against the checksums of its frames",
                       description=__doc__)
    v.add_argument("store", help="the OME-Zarr store a series job wrote (OUT.ome.zarr)")
    v.set_defaults(func=command)
    return v


def command(args) -> int:
    from ..jobs.store import FrameStore

    store = FrameStore.open_readonly(args.store)
    done = sorted(store.done())
    bad = store.verify(done)
    unchecked = sum(1 for i in done if i not in bad and "sha256" not in _info(store, i))
    print(f"{args.store}: {len(done)} of {store.n_frames} frames done, {len(done) - len(bad) - unchecked} match their "
          f"checksums" + (f", {unchecked} written without one (checked only to decode)" if unchecked else "")
          + (f", {len(bad)} do not" if bad else ""))
    if bad:
        shown = ", ".join(map(str, bad[:20])) + (", ..." if len(bad) > 20 else "")
        print(f"cm2cl: error: store '{args.store}': frame(s) {shown} do not match their checksums or cannot be "
              "decoded (lost or overwritten chunks); rerun the job's command to compute them again", file=sys.stderr)
        return 1
    return 0


def _info(store, i) -> dict:
    try:
        return store.info(i)
    except (ValueError, OSError):
        return {}
