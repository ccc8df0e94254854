"""Object storage against folders: the tiny session run from and into an S3 bucket.

    python benchmarks/objstore.py [--repeats 3] [--modes serial,dask-2] [--sessions tiny,demo]

Renders the tests' tiny session (4 cameras x 3 frames at 192x144) and the demo's (8
cameras x 4 frames at 480x360), starts moto's S3 server on 127.0.0.1 (the test extra's
``moto[server]``), uploads each session to a bucket and, for each mode, reconstructs it
alternately

* ``folder``: session folder -> folder store (chunk files written by storage/chunkio.py);
* ``s3``: session in the bucket -> store in the bucket (zarr's FsspecStore, s3fs),

each run into a fresh store, ``--repeats`` times; the best (and median) wall time of each
and their ratio are reported, with the requests the server answered per S3 run.
``serial`` is the reference loop in this process; ``dask-2`` a local cluster of two
workers started once (start-up excluded, as in benchmarks/scaling.py). A first run of
each kind warms imports and compiled kernels and is not counted. The server is a Python
process sharing this machine's cores with the run: a real object store costs the run
no CPU but more latency per request.

Writes ``benchmarks/results/objstore.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
SESSIONS = {
    #: the tests' tiny session (tests/conftest.py TINY): about 8 ms of compute per chunk
    "tiny": dict(cameras=4, ring="half", phantom="blob", frames=3, size=(192, 144), seed=3,
                 recon_voxel=0.005, supersample=2),
    #: ``schlieren demo``'s session
    "demo": dict(cameras=8, ring="half", phantom="plume", frames=4, size=(480, 360), seed=0),
}


def start_server(log_path: Path) -> tuple[subprocess.Popen, str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"http://127.0.0.1:{port}"
    log = open(log_path, "wb")  # noqa: SIM115 - the server's request log, read between runs
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=log, stderr=subprocess.STDOUT)
    deadline = time.time() + 60
    while True:
        try:
            with urllib.request.urlopen(f"{endpoint}/moto-api/", timeout=2):
                return proc, endpoint
        except OSError:
            if proc.poll() is not None or time.time() > deadline:
                proc.kill()
                raise SystemExit(f"moto's S3 server did not start on {endpoint} (pip install 'moto[server]')")
            time.sleep(0.2)


def requests_in(log_path: Path, start: int) -> tuple[int, dict[str, int]]:
    """Requests the server logged from byte ``start`` on: (end offset, counts by method)."""
    data = log_path.read_bytes()
    counts: dict[str, int] = {}
    for line in data[start:].decode(errors="replace").splitlines():
        for method in ("GET", "PUT", "HEAD", "DELETE", "POST"):
            if f'"{method} /' in line:
                counts[method] = counts.get(method, 0) + 1
    return len(data), counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--modes", default="serial,dask-2")
    ap.add_argument("--sessions", default="tiny,demo")
    ap.add_argument("--workdir", default=None)
    args = ap.parse_args(argv)
    # a temporary folder is removed at the end (its sessions, stores and the staged geometry
    # caches of the bucket runs: 2.7 GB for the default sessions and repeats); --workdir is kept
    work = Path(args.workdir or tempfile.mkdtemp(prefix="schlieren-objstore-"))
    work.mkdir(parents=True, exist_ok=True)
    log_path = work / "s3-server.log"
    proc, endpoint = start_server(log_path)
    os.environ.update(AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench", AWS_DEFAULT_REGION="us-east-1",
                      AWS_ENDPOINT_URL=endpoint)
    os.environ.setdefault("SCHLIEREN_CACHE_DIR", str(work / "stage-cache"))
    try:
        return _run(args, work, log_path, proc.pid)
    finally:
        proc.terminate()
        proc.wait(10)
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)


def _run(args, work: Path, log_path: Path, proc_pid: int) -> int:
    import fsspec

    from schlieren.workers.synth import synthesize

    fs = fsspec.filesystem("s3", endpoint_url=os.environ["AWS_ENDPOINT_URL"])
    fs.mkdir("bench")
    results: dict[str, dict] = {}
    floors: dict[str, dict] = {}
    for name in [n.strip() for n in args.sessions.split(",") if n.strip()]:
        session = work / f"session-{name}"
        if not (session / "session.yaml").exists():
            synthesize(session, **SESSIONS[name])
        fs.put(f"{session}/", f"bench/session-{name}/", recursive=True)
        for mode, r in _modes(args, work, log_path, session, f"s3://bench/session-{name}").items():
            results[f"{name} {mode}"] = r
        puts = max(r["requests_per_s3_run"].get("PUT", 0) for m, r in results.items() if m.startswith(name + " "))
        floors[name] = bare_puts(fs, f"bench/bare-{name}", puts, fs.glob(f"bench/run-{session.name}-*.zarr")[0],
                                 args.repeats, proc_pid)
    return _write(args, results, floors)


def bare_puts(fs, prefix: str, n: int, like: str, repeats: int, server_pid: int) -> dict:
    """The server's price of a run's PUTs alone: ``n`` objects of the mean size of the objects
    of store ``like``, sent one after another and 8 at a time, with nothing else running
    (best of ``repeats``); the client's and the server's CPU seconds."""
    import psutil

    found = fs.find(like, detail=True)
    size = int(sum(int(v.get("size") or 0) for v in found.values()) / max(1, len(found)))
    blob = os.urandom(size)
    server = psutil.Process(server_pid)
    out: dict = {"objects": n, "bytes_each": size}
    for kind in ("sequential", "concurrent"):
        best = None
        for r in range(repeats):
            c0, s0, t0 = time.process_time(), sum(server.cpu_times()[:2]), time.perf_counter()
            if kind == "sequential":
                for i in range(n):
                    fs.pipe_file(f"{prefix}/{kind}{r}/{i}", blob)
            else:
                fs.pipe({f"{prefix}/{kind}{r}/{i}": blob for i in range(n)}, batch_size=8)
            got = (time.perf_counter() - t0, time.process_time() - c0, sum(server.cpu_times()[:2]) - s0)
            best = got if best is None or got[0] < best[0] else best
        out[kind] = {"wall_s": round(best[0], 3), "client_cpu_s": round(best[1], 3),
                     "server_cpu_s": round(best[2], 3)}
    return out


def _modes(args, work: Path, log_path: Path, session: Path, s3_session: str) -> dict[str, dict]:
    from schlieren.workers.cluster import ClusterOptions, open_client
    from schlieren.workers.run import run_session

    results: dict[str, dict] = {}
    counter = [0]

    def one(kind: str, client) -> tuple[float, dict]:
        counter[0] += 1
        if kind == "folder":
            src, out = session, work / f"run-{session.name}-{counter[0]}.zarr"
        else:
            src, out = s3_session, f"s3://bench/run-{session.name}-{counter[0]}.zarr"
        start, _ = requests_in(log_path, 0)
        t0 = time.perf_counter()
        s = run_session(src, out, client=client, serial=client is None)
        dt = time.perf_counter() - t0
        if not s.ok:
            raise SystemExit(f"{kind}: run failed: {s.root_failures()}")
        _, counts = requests_in(log_path, start)
        if kind == "folder":
            shutil.rmtree(out, ignore_errors=True)
        return dt, counts

    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        n = 0 if mode == "serial" else int(mode.split("-")[1])
        ctx = open_client(ClusterOptions(workers=n)) if n else None
        client = ctx.__enter__()[0] if ctx else None
        try:
            times: dict[str, list[float]] = {"folder": [], "s3": []}
            reqs: list[dict] = []
            for kind in ("folder", "s3"):  # warm-up, not counted
                one(kind, client)
            for i in range(args.repeats):
                for kind in ("folder", "s3") if i % 2 == 0 else ("s3", "folder"):
                    dt, counts = one(kind, client)
                    times[kind].append(round(dt, 3))
                    if kind == "s3":
                        reqs.append(counts)
                    print(f"{session.name} {mode} {kind} run {i}: {dt:.2f} s", file=sys.stderr)
        finally:
            if ctx:
                ctx.__exit__(None, None, None)
        best = {k: min(v) for k, v in times.items()}
        results[mode] = {
            "runs_s": times,
            "best_s": best,
            "median_s": {k: statistics.median(v) for k, v in times.items()},
            "ratio_best": round(best["s3"] / best["folder"], 3),
            "ratio_median": round(statistics.median(times["s3"]) / statistics.median(times["folder"]), 3),
            "requests_per_s3_run": reqs[-1] if reqs else {},
        }
    return results


def _write(args, results: dict[str, dict], floors: dict[str, dict]) -> int:
    out = {
        "sessions": {k: {kk: list(v) if isinstance(v, tuple) else v for kk, v in d.items()}
                     for k, d in SESSIONS.items() if k in args.sessions},
        "server": "moto (Python S3 server) on 127.0.0.1, sharing the machine's cores",
        "repeats": args.repeats,
        "results": results,
        "bare_puts": floors,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_average_after": list(os.getloadavg())},
        "command": "python benchmarks/objstore.py " + " ".join(argv_or_default(args)),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "objstore.json").write_text(json.dumps(out, indent=2) + "\n")
    lines = ["# Object storage vs folders", "",
             "Sessions: tiny = the tests' (4 cameras x 3 frames, 192x144); demo = `schlieren demo`'s "
             "(8 cameras x 4 frames, 480x360). Folder: session folder -> folder store; S3: session in a "
             "bucket -> store in a bucket.", "",
             f"moto's S3 server on 127.0.0.1; best of {args.repeats} runs each after a warm-up run "
             "(folder and S3 runs alternate); load average after the runs "
             f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} cores.", "",
             "| session, mode | folder best (s) | S3 best (s) | S3 / folder best | S3 / folder median "
             "| requests per S3 run |",
             "| --- | --- | --- | --- | --- | --- |"]
    for mode, r in results.items():
        req = ", ".join(f"{k} {v}" for k, v in sorted(r["requests_per_s3_run"].items()))
        lines.append(f"| {mode} | {r['best_s']['folder']:.2f} | {r['best_s']['s3']:.2f} | {r['ratio_best']:.2f} | "
                     f"{r['ratio_median']:.2f} | {req} |")
    lines += ["", "The server's price of those PUTs alone (the store's objects cannot be fewer: an S3 store "
              "holds the folder store's files, one object each): as many objects of the store's mean size, "
              "sent with nothing else running, one after another and 8 at a time (best of "
              f"{args.repeats}), and the CPU seconds of this process (botocore) and of the server.", "",
              "| session | PUTs x bytes | one by one (s) | 8 at a time (s) | client CPU (s) | server CPU (s) "
              "| 8 at a time / folder run (serial) |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, f in floors.items():
        folder = results.get(f"{name} serial", next(iter(results.values())))["best_s"]["folder"]
        c = f["concurrent"]
        lines.append(f"| {name} | {f['objects']} x {f['bytes_each']} | {f['sequential']['wall_s']:.2f} | "
                     f"{c['wall_s']:.2f} | {c['client_cpu_s']:.2f} | {c['server_cpu_s']:.2f} | "
                     f"{c['wall_s'] / folder:.2f} |")
    lines += ["", f"Command: `{out['command']}`", ""]
    (RESULTS / "objstore.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


def argv_or_default(args) -> list[str]:
    return [f"--repeats {args.repeats}", f"--modes {args.modes}", f"--sessions {args.sessions}"]


if __name__ == "__main__":
    sys.exit(main())
