"""The benchmark family's predicted flow noise: what ``schlieren check`` compares a rig with.

    python benchmarks/check_family.py [--work /work/realistic] [--results benchmarks/results]

For each case of the family's ``realistic.json`` whose rendered session is under
``--work`` (``<work>/<case>/session.yaml``), reads the references of its first
``--cameras`` cameras as ``schlieren check`` does and records the median over them of
the sensor noise (grey levels), the reference frames and the predicted flow noise (pixels, over the
volume's footprint) for each LK window of ``WINDOWS``, with the run's other flow
parameters: what the family's in-focus background gives at a window and a noise.
``schlieren check`` reads them (``check_family.json``) to judge a rig's own predicted
flow noise (:mod:`schlieren.pipeline.rigcheck.expect`). Writes ``check_family.json``
and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


WINDOWS = (5, 7, 9, 11, 13, 15, 17, 19, 21, 25)


def case_flow_noise(session_dir: Path, cameras: int) -> dict:
    from schlieren.pipeline.flow.params import FlowParams
    from schlieren.pipeline.rigcheck.camera import _flow_noise, footprint
    from schlieren.pipeline.rigcheck.noise import sensor_noise
    from schlieren.storage.rigcheck import camera_inputs
    from schlieren.storage.session import load_session

    session = load_session(session_dir, check_files=False)
    flow = FlowParams()
    noise, n_ref, by_window = [], [], {w: [] for w in WINDOWS}
    for c in range(min(cameras, len(session.cameras))):
        inp = camera_inputs(session, c, motion_frames=0)
        refs = inp.reference_frames
        s = sensor_noise(refs, full_scale=inp.full_scale)
        noise.append(s)
        n_ref.append(inp.n_reference)
        fp = footprint(session.cameras[c], session.grid)
        for w in WINDOWS:
            by_window[w].append(_flow_noise(refs.mean(axis=0), fp, noise=s, n_reference=inp.n_reference, window=w,
                                            flow=flow))
    return {"noise": float(np.median(noise)), "cameras": len(noise), "n_reference": int(np.median(n_ref)),
            "flow_noise": {str(w): float(np.median(v)) for w, v in by_window.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/work/realistic")
    ap.add_argument("--results", default=str(HERE / "results"))
    ap.add_argument("--cameras", type=int, default=4)
    args = ap.parse_args(argv)
    results = Path(args.results)
    cases = [c["case"] for c in json.loads((results / "realistic.json").read_text())["cases"]]
    out = {}
    for case in cases:
        session = Path(args.work) / case
        if not (session / "session.yaml").is_file():
            print(f"{case}: no session under {args.work}", file=sys.stderr)
            continue
        out[case] = case_flow_noise(session, args.cameras)
        print(case, out[case], flush=True)
    command = f"python benchmarks/check_family.py --work {args.work} --cameras {args.cameras}"
    (results / "check_family.json").write_text(json.dumps({"command": command, "cases": out}, indent=1) + "\n")
    lines = ["# The benchmark family's predicted flow noise, by LK window", "",
             "What `schlieren check` judges a rig's predicted flow noise by (`pipeline/rigcheck/expect.py`): the "
             "median over each family case's first cameras of the check's predicted flow noise (pixels, per "
             "component, median over the volume's footprint) for each LK window, at the case's sensor noise, with "
             "the run's other flow parameters and the case's reference frames. The family's backgrounds are the "
             "renderer's in-focus Wavelet Noise.", "",
             f"Command: `{command}`", "",
             "| case | cameras | reference frames | sensor noise grey | "
             + " | ".join(f"window {w}" for w in WINDOWS) + " |",
             "|---|---:|---:|---:|" + "---:|" * len(WINDOWS)]
    lines += [f"| {k} | {v['cameras']} | {v['n_reference']} | {v['noise']:.2f} | "
              + " | ".join(f"{v['flow_noise'][str(w)]:.4f}" for w in WINDOWS) + " |" for k, v in out.items()]
    (results / "check_family.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
