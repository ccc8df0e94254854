"""Store size per time step at paper scale for each retention choice (issue 36, build item 5).

    python benchmarks/retention.py [--frames 4] [--keep all flow results]

1. Renders (once; cached in ``benchmarks/cache/``, which git ignores) the paper-scale
   session of benchmarks/session.py with fewer frames: 16 cameras on a half ring at
   1440x1080, the buoyant plume, the paper's volume at 2.5 mm (``schlieren synth``'s
   defaults), ``--frames`` processed frames (4 + N + 2 raw frames rendered).
2. Runs ``schlieren run --serial --keep K`` into a fresh store for each ``K``, sampling
   the store's size on disk every 0.2 s during the run (its peak), and measures the
   finished store per array. The volumes of every run are compared with the first run's
   (retention never changes results).
3. Reports per time step: the finished store divided by the frames; the long-run figure
   (each array's chunks at the processed frames, divided by their number: ``flow_raw``
   also holds up to 4 margin raw frames, which a long capture amortises; arrays without
   a frame axis are once per session and left out); and the peak during the run. The tomography geometry (``<store>.cache``, once per session) is reported
   apart.

Writes ``benchmarks/results/retention.json`` and ``.md``. Sizes are bytes on disk (zstd
and CRC-32C chunks as the run writes them) and do not depend on the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from session import CACHE, RESULTS, ensure_session, fresh_store, store_size  # noqa: E402

POLICIES = ("all", "flow", "results")
VOLUMES = ("hull", "gradient", "refractivity", "density", "temperature")
FRAME_AXES = ("frame", "raw_frame")


def _tree_bytes(path: Path) -> int:
    total = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += (Path(root) / f).stat().st_size
            except OSError:  # removed meanwhile (a dropped chunk)
                pass
    return total


class SizeSampler:
    """Peak bytes of a folder, sampled in a thread."""

    def __init__(self, path: Path, interval: float = 0.2):
        self.path, self.interval, self.peak = path, interval, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self):
        while not self._stop.is_set():
            if self.path.exists():
                self.peak = max(self.peak, _tree_bytes(self.path))
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        if self.path.exists():
            self.peak = max(self.peak, _tree_bytes(self.path))


def processed_frame_bytes(store: Path) -> dict[str, int]:
    """Per array with a frame axis (``frame`` or ``raw_frame``): the bytes of its chunks at
    the processed frames (a raw frame's chunks count when it is one of them, so the margin
    raw frames, which a long capture amortises, are left out)."""
    root = json.loads((store / "zarr.json").read_text())["attributes"]
    run = root["run"] if isinstance(root["run"], dict) else json.loads(root["run"])
    first, raw_first, n = int(run["frames"][0]), int(run["raw_first"]), int(run["n_frames"])
    out = {}
    for meta in store.glob("*/zarr.json"):
        m = json.loads(meta.read_text())
        dims = m.get("dimension_names") or []
        axis = next((a for a in FRAME_AXES if a in dims), None)
        if m.get("node_type") != "array" or axis is None:
            continue
        k = dims.index(axis)
        lo = first - raw_first if axis == "raw_frame" else 0
        total = 0
        for f in (meta.parent / "c").rglob("*"):
            parts = f.relative_to(meta.parent / "c").parts
            if f.is_file() and len(parts) == len(dims) and lo <= int(parts[k]) < lo + n:
                total += f.stat().st_size
        out[meta.parent.name] = total
    return out


def run_policy(session: Path, store: Path, keep: str, frames: int) -> dict:
    fresh_store(store)
    cmd = [sys.executable, "-m", "schlieren.workers.cli", "run", str(session), "--out", str(store), "--serial",
           "--no-progress", "--keep", keep]
    t0 = time.time()
    with SizeSampler(store) as sampler:
        proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"run --keep {keep} failed:\n{proc.stderr}")
    size = store_size(store)
    per_step = {a: b / frames for a, b in processed_frame_bytes(store).items()}
    return {"keep": keep, "seconds": round(time.time() - t0, 1), "command": " ".join(cmd[1:]),
            "results_bytes": size["results_bytes"], "cache_bytes": size["cache_bytes"],
            "peak_bytes": sampler.peak, "arrays_bytes": size["arrays_bytes"],
            "per_step_bytes": size["results_bytes"] / frames,
            "long_run_per_step_bytes": sum(per_step.values()),
            "arrays_per_step_bytes": dict(sorted(per_step.items(), key=lambda kv: -kv[1]))}


def same_volumes(a: Path, b: Path) -> bool:
    import numpy as np
    import zarr

    ga, gb = zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r")
    return all(np.array_equal(np.asarray(ga[v][...]), np.asarray(gb[v][...]), equal_nan=True) for v in VOLUMES)


def _mb(n: float) -> str:
    return f"{n / 1e6:.2f}"


def markdown(res: dict) -> str:
    F = res["frames"]
    md = ["# Store size per time step for each retention choice", "",
          f"Paper scale: {res['session']} ({F} processed frames, {F + 6} raw frames rendered). "
          f"Command: `{res['command']}` (each run: `schlieren run SESSION --out STORE --serial --keep K`). "
          f"Measured {res['date']} on {res['machine']}; sizes are bytes on disk and do not depend on the "
          "machine's load. Every run's volumes equal the first run's bit for bit: "
          f"{'yes' if res['volumes_identical'] else 'NO'}.", "",
          "| --keep | store MB per time step (finished store / frames) | long run MB per time step "
          "(chunks of the processed frames / frames) | peak MB on disk during the run | 1000 frames GB (long run) |",
          "| --- | ---: | ---: | ---: | ---: |"]
    for r in res["runs"]:  # (the runs' seconds are in the JSON: a loaded machine's, not a timing)
        md.append(f"| `{r['keep']}` | {_mb(r['per_step_bytes'])} | {_mb(r['long_run_per_step_bytes'])} | "
                  f"{_mb(r['peak_bytes'])} | {r['long_run_per_step_bytes'] * 1000 / 1e9:.1f} |")
    first = res["runs"][0]
    md += ["", f"Plus the tomography geometry beside the store (`STORE.cache`, once per session, "
               f"removable with `schlieren clean`): {_mb(first['cache_bytes'])} MB.", "",
           "Long-run MB per time step of each array (`--keep all`):", "",
           "| array | MB per time step |", "| --- | ---: |"]
    for a, b in first["arrays_per_step_bytes"].items():
        if b >= 1e4:
            md.append(f"| `{a}` | {_mb(b)} |")
    md += ["", "`all` keeps every array (the default, as before); `flow` keeps the resampled flow (the report's "
               "deflection and residual figures) and drops `flow_raw` and `potential`; `results` keeps the "
               "volumes, masks, hulls and the small per-frame arrays. Dropped chunks are deleted as soon as "
               "every task reading them is done, so the peak on disk of a long run stays near the kept size plus "
               "the frames in flight; with the few frames here the peak is reached before the first solve. "
               "docs/store.md, \"Retention\"."]
    return "\n".join(md) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=4, help="processed frames of the rendered session (default 4)")
    ap.add_argument("--keep", nargs="+", default=list(POLICIES), help="retention choices to measure")
    args = ap.parse_args(argv)
    F = args.frames
    CACHE.mkdir(parents=True, exist_ok=True)
    session = CACHE / f"retention-16x{F}"
    render = ensure_session(session, cameras=16, frames=F, size=(1440, 1080))
    runs, stores = [], []
    for keep in args.keep:
        store = CACHE / f"retention-{keep.replace(',', '_')}.zarr"
        print(f"run --keep {keep} ...", file=sys.stderr)
        runs.append(run_policy(session, store, keep, F))
        stores.append(store)
    identical = all(same_volumes(stores[0], s) for s in stores[1:])
    res = {"frames": F, "session": "16 cameras 1440x1080, half ring, plume, the paper's volume at 2.5 mm",
           "command": "python benchmarks/retention.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.node()} ({os.cpu_count()} cores)",
           "render": render, "volumes_identical": identical, "runs": runs}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "retention.json").write_text(json.dumps(res, indent=1) + "\n")
    (RESULTS / "retention.md").write_text(markdown(res))
    print(markdown(res))
    for s in stores:
        fresh_store(s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
