"""Object storage against folders: the tiny session run from and into an S3 bucket.

    python benchmarks/objstore.py [--repeats 3] [--modes serial,dask-2] [--sessions tiny,demo]
                                  [--servers moto,moto-keepalive]

Renders the tests' tiny session (4 cameras x 3 frames at 192x144) and the demo's (8
cameras x 4 frames at 480x360), starts a local S3 server on 127.0.0.1, uploads each
session to a bucket and, for each mode, reconstructs it alternately

* ``folder``: session folder -> folder store (chunk files written by storage/chunkio.py);
* ``s3``: session in the bucket -> store in the bucket (the same bytes, s3fs),

each run into a fresh store, ``--repeats`` times; the best (and median) wall time of each
and their ratio are reported, with the requests the server answered per S3 run.
``serial`` is the reference loop in this process; ``dask-2`` a local cluster of two
workers started once (start-up excluded, as in benchmarks/scaling.py). A first run of
each kind warms imports and compiled kernels and is not counted.

Servers (``--servers``): ``moto`` is ``python -m moto.server`` (the tests' server:
Werkzeug's development server, which closes the connection after every request);
``moto-keepalive`` is the same moto application behind waitress with HTTP/1.1 keep-alive
(benchmarks/s3_keepalive.py), as S3, MinIO and Ceph serve. Either is a Python process
sharing this machine's two cores with the run: a real object store costs the run no CPU
but more latency per request.

The lower bound (``replay``): the S3 run's requests without the pipeline around them:
every object of the S3 run's store PUT again (same sizes, 8 at a time, s3fs's own batch)
and the objects the S3 run read (frames, metadata) read again, first alone, then in a thread of this process while a
folder run computes. No client can do the S3 run's requests for less on this machine and
server; "folder run + replay" is what a perfect overlap of them with the computation
would cost.

Writes ``benchmarks/results/objstore.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import re
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
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


_RUNS = itertools.count(1)

SERVERS = {
    "moto": "moto's own server (Werkzeug development server: a new connection per request)",
    "moto-keepalive": "moto's S3 behind waitress, HTTP/1.1 keep-alive (benchmarks/s3_keepalive.py)",
}


def start_server(log_path: Path, kind: str = "moto") -> tuple[subprocess.Popen, str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"http://127.0.0.1:{port}"
    log = open(log_path, "wb")  # noqa: SIM115 - the server's request log, read between runs
    if kind == "moto":
        cmd = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)]
    elif kind == "moto-keepalive":
        cmd = [sys.executable, str(Path(__file__).with_name("s3_keepalive.py")), "127.0.0.1", str(port)]
    else:
        raise SystemExit(f"unknown server {kind!r} (one of {', '.join(SERVERS)})")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    deadline = time.time() + 60
    while True:
        try:
            with urllib.request.urlopen(f"{endpoint}/moto-api/", timeout=2):
                return proc, endpoint
        except OSError:
            if proc.poll() is not None or time.time() > deadline:
                proc.kill()
                raise SystemExit(f"{kind}: the S3 server did not start on {endpoint} "
                                 "(pip install 'moto[server]' waitress)")
            time.sleep(0.2)


_REQUEST = re.compile(r'"(GET|PUT|HEAD|DELETE|POST) (/[^ "?]*)(\?[^ "]*)?')
_ANSI = re.compile(r"\x1b\[[0-9;]*m")  # Werkzeug colours the lines of non-200 answers


def requests_in(log_path: Path, start: int) -> tuple[int, dict[str, int], list[str]]:
    """Requests the server logged from byte ``start`` on: (end offset, counts by method,
    the paths of the objects read: GETs without a query, which listings have)."""
    data = log_path.read_bytes()
    counts: dict[str, int] = {}
    read: list[str] = []
    for line in _ANSI.sub("", data[start:].decode(errors="replace")).splitlines():
        m = _REQUEST.search(line)
        if m:
            counts[m.group(1)] = counts.get(m.group(1), 0) + 1
            if m.group(1) == "GET" and not m.group(3):
                read.append(m.group(2).lstrip("/"))
    return len(data), counts, read


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--modes", default="serial,dask-2")
    ap.add_argument("--sessions", default="tiny,demo")
    ap.add_argument("--servers", default="moto,moto-keepalive")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # SERVER,SESSION,JSON: a child's part
    args = ap.parse_args(argv)
    if args.one:
        return _one(args)
    # a temporary folder is removed at the end (its sessions, stores and the staged geometry
    # caches of the bucket runs: 2.7 GB for the default sessions and repeats); --workdir is kept
    work = Path(args.workdir or tempfile.mkdtemp(prefix="schlieren-objstore-"))
    work.mkdir(parents=True, exist_ok=True)
    out: dict[str, dict] = {}
    try:
        # each server and session in a fresh process, the small session first for every server:
        # after the demo's runs (GBs written and staged) this VM ran the tiny session's folder
        # runs at half speed for minutes, which shrank that session's ratios
        for name in [n.strip() for n in args.sessions.split(",") if n.strip()]:
            for kind in [k.strip() for k in args.servers.split(",") if k.strip()]:
                part = out.setdefault(kind, {"results": {}, "replay": {}})
                got = work / f"part-{kind}-{name}.json"
                cmd = [sys.executable, __file__, "--one", f"{kind},{name},{got}", "--workdir", str(work),
                       *" ".join(argv_or_default(args)).split()]
                if subprocess.run(cmd).returncode != 0:
                    raise SystemExit(f"{kind} {name}: the benchmark's run failed")
                one = json.loads(got.read_text())
                part["results"].update(one["results"])
                part["replay"].update(one["replay"])
    finally:
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)
    return _write(args, out)


def _one(args) -> int:
    """One server and one session (a child process of :func:`main`): results as JSON."""
    kind, name, got = args.one.split(",", 2)
    work = Path(args.workdir)
    os.environ.update(AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench", AWS_DEFAULT_REGION="us-east-1")
    os.environ.setdefault("SCHLIEREN_CACHE_DIR", str(work / "stage-cache"))
    log_path = work / f"s3-server-{kind}-{name}.log"
    proc, endpoint = start_server(log_path, kind)
    os.environ["AWS_ENDPOINT_URL"] = endpoint
    args.sessions = name
    try:
        Path(got).write_text(json.dumps(_run(args, work, log_path, proc.pid, endpoint)))
    finally:
        proc.terminate()
        proc.wait(10)
    return 0


def _run(args, work: Path, log_path: Path, proc_pid: int, endpoint: str) -> dict:
    from schlieren.storage import location
    from schlieren.workers.synth import synthesize

    fs, _ = location.filesystem("s3://bench/x")  # the client the runs use (storage/location.py)
    fs.mkdir("bench")
    results: dict[str, dict] = {}
    replays: dict[str, dict] = {}
    for name in [n.strip() for n in args.sessions.split(",") if n.strip()]:
        session = work / f"session-{name}"
        if not (session / "session.yaml").exists():
            synthesize(session, **SESSIONS[name])
        fs.put(f"{session}/", f"bench/session-{name}/", recursive=True)
        modes = [m.strip() for m in args.modes.split(",") if m.strip()]
        # the serial runs, then the replay, then the clusters: after a local Dask cluster has
        # run and closed, this process ran folder runs up to 1.5x slower
        parts = ([m for m in modes if m == "serial"], None, [m for m in modes if m != "serial"]) \
            if "serial" in modes else (modes, None)
        for part in parts:
            if part is None:
                store = sorted(fs.glob(f"bench/run-{session.name}-*.zarr"))[-1]
                read = next(r for m, r in results.items() if m.startswith(name + " "))["objects_read_per_s3_run"]
                replays[name] = replay(fs, store, read, session, work, args.repeats, proc_pid)
                continue
            for mode, r in _modes(args, work, log_path, session, f"s3://bench/session-{name}", part).items():
                results[f"{name} {mode}"] = r
    for r in results.values():  # the replay's list; the results keep its length
        r["objects_read_per_s3_run"] = len(r["objects_read_per_s3_run"])
    return {"results": results, "replay": replays}


def replay(fs, store: str, read: list[str], session: Path, work: Path, repeats: int, server_pid: int) -> dict:
    """The S3 run's requests alone, and alongside a folder run (see the module doc): every
    object of ``store`` and of its geometry cache PUT again with the same sizes (8 at a
    time) and the objects of ``read`` (what the S3 run read) read again, 8 at a time; best
    of ``repeats``, with the client's and the server's CPU seconds of the replay alone."""
    import psutil

    from schlieren.workers.run import run_session

    objects = {**fs.find(store, detail=True), **fs.find(store + ".cache", detail=True)}
    blobs = [os.urandom(int(v.get("size") or 0)) for v in objects.values()]
    frames = [p for p in read if fs.exists(p)]  # not what the run asked for before it existed
    server = psutil.Process(server_pid)
    counter = [0]

    def requests() -> None:
        counter[0] += 1
        fs.pipe({f"bench/replay-{counter[0]}/{i}": b for i, b in enumerate(blobs)}, batch_size=8)
        fs.cat(frames, batch_size=8)

    alone, both, folder = [], [], []
    for r in range(repeats + 1):  # the first of each: a warm-up, not counted
        c0, s0, t0 = time.process_time(), sum(server.cpu_times()[:2]), time.perf_counter()
        requests()
        got = (time.perf_counter() - t0, time.process_time() - c0, sum(server.cpu_times()[:2]) - s0)
        out = work / f"replay-{session.name}.zarr"
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        run_session(session, out, serial=True)
        f = time.perf_counter() - t0
        shutil.rmtree(out, ignore_errors=True)
        th = threading.Thread(target=requests)
        t0 = time.perf_counter()
        th.start()
        run_session(session, out, serial=True)
        th.join()
        b = time.perf_counter() - t0
        shutil.rmtree(out, ignore_errors=True)
        if r:
            alone.append(got)
            folder.append(f)
            both.append(b)
    best = min(alone)
    return {"puts": len(blobs), "bytes": sum(len(b) for b in blobs), "gets": len(frames),
            "alone_s": round(best[0], 3), "client_cpu_s": round(best[1], 3), "server_cpu_s": round(best[2], 3),
            "folder_s": [round(x, 3) for x in folder], "folder_and_replay_s": [round(x, 3) for x in both],
            "ratio_best": round(min(both) / min(folder), 3),
            "ratio_median": round(statistics.median(both) / statistics.median(folder), 3),
            "ratio_paired_median": round(statistics.median(b / a for a, b in zip(folder, both)), 3)}


def _modes(args, work: Path, log_path: Path, session: Path, s3_session: str, modes: list[str]) -> dict[str, dict]:
    from schlieren.workers.cluster import ClusterOptions, open_client
    from schlieren.workers.run import run_session

    results: dict[str, dict] = {}
    last_read: list[str] = []

    def one(kind: str, client) -> tuple[float, dict]:
        n = next(_RUNS)  # unique across servers too: a store path is never reused in this process
        if kind == "folder":
            src, out = session, work / f"run-{session.name}-{n}.zarr"
        else:
            src, out = s3_session, f"s3://bench/run-{session.name}-{n}.zarr"
        start, _, _ = requests_in(log_path, 0)
        t0 = time.perf_counter()
        s = run_session(src, out, client=client, serial=client is None)
        dt = time.perf_counter() - t0
        if not s.ok:
            raise SystemExit(f"{kind}: run failed: {s.root_failures()}")
        _, counts, read = requests_in(log_path, start)
        if kind == "folder":
            shutil.rmtree(out, ignore_errors=True)
        else:
            last_read[:] = read
        return dt, counts

    for mode in modes:
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
            # each repeat's two runs follow each other: their ratio is the least disturbed by the
            # machine's speed drifting between repeats (2x within minutes on a shared VM)
            "ratio_paired_median": round(statistics.median(b / a for a, b in zip(times["folder"], times["s3"])), 3),
            "requests_per_s3_run": reqs[-1] if reqs else {},
            "objects_read_per_s3_run": list(last_read),
        }
    return results


def _write(args, out: dict[str, dict]) -> int:
    doc = {
        "sessions": {k: {kk: list(v) if isinstance(v, tuple) else v for kk, v in d.items()}
                     for k, d in SESSIONS.items() if k in args.sessions},
        "servers": {k: SERVERS[k] for k in out},
        "repeats": args.repeats,
        "by_server": out,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_average_after": list(os.getloadavg())},
        "command": "python benchmarks/objstore.py " + " ".join(argv_or_default(args)),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "objstore.json").write_text(json.dumps(doc, indent=2) + "\n")
    lines = ["# Object storage vs folders", "",
             "Sessions: tiny = the tests' (4 cameras x 3 frames, 192x144); demo = `schlieren demo`'s "
             "(8 cameras x 4 frames, 480x360). Folder: session folder -> folder store; S3: session in a "
             "bucket -> store in a bucket.", "",
             f"S3 servers on 127.0.0.1, sharing the {os.cpu_count()} cores with the run; best of "
             f"{args.repeats} runs each after a warm-up run (folder and S3 runs alternate); load average "
             f"after the runs {', '.join(f'{x:.1f}' for x in os.getloadavg())}.", ""]
    for kind, d in out.items():
        lines += [f"## {kind}: {SERVERS[kind]}", "",
                  "| session, mode | folder best (s) | S3 best (s) | S3 / folder: best | medians "
                  "| median of pairs | requests per S3 run |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for mode, r in d["results"].items():
            req = ", ".join(f"{k} {v}" for k, v in sorted(r["requests_per_s3_run"].items()))
            lines.append(f"| {mode} | {r['best_s']['folder']:.2f} | {r['best_s']['s3']:.2f} | "
                         f"{r['ratio_best']:.2f} | {r['ratio_median']:.2f} | {r['ratio_paired_median']:.2f} | {req} |")
        lines += ["", "The lower bound: the S3 run's objects PUT again (same sizes, 8 at a time) and its "
                  "frames read, alone and in a thread beside a serial folder run (best of "
                  f"{args.repeats}); CPU seconds of the replay alone.", "",
                  "| session | PUTs, GETs, MB | replay alone (s) | client CPU (s) | server CPU (s) "
                  "| folder run best (s) | folder run + replay best (s) | (folder + replay) / folder: best "
                  "| medians | median of pairs |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for name, f in d["replay"].items():
            lines.append(f"| {name} | {f['puts']}, {f['gets']}, {f['bytes'] / 1e6:.1f} | {f['alone_s']:.2f} | "
                         f"{f['client_cpu_s']:.2f} | {f['server_cpu_s']:.2f} | {min(f['folder_s']):.2f} | "
                         f"{min(f['folder_and_replay_s']):.2f} | {f['ratio_best']:.2f} | {f['ratio_median']:.2f} | "
                         f"{f['ratio_paired_median']:.2f} |")
        lines.append("")
    lines += [f"Command: `{doc['command']}`", ""]
    (RESULTS / "objstore.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


def argv_or_default(args) -> list[str]:
    return [f"--repeats {args.repeats}", f"--modes {args.modes}", f"--sessions {args.sessions}",
            f"--servers {args.servers}"]


if __name__ == "__main__":
    sys.exit(main())
