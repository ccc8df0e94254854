"""What each lab effect of the realistic family costs after the capture corrections (issue 33).

    python benchmarks/lab_gap.py --work /work/scratch-labgap --variants laball-16ref,laball-noroll,...
        [--params FILE] [--label NAME]

Renders variants of the family's lab cases with one effect switched off (or on) through the
family's own renderer (workers/bench/realistic_render.py: same flow, rig, scale and sensor noise
stream as the family case; the lab effects drawn from the same stream, so an effect switched
off leaves the others' draws as they were, but for the defect counts and the reference-frame
count, which shift the later draws), into ``--work`` (never /work/realistic), runs the pipeline
with the defaults (or ``--params``) and scores them against their truth as the bench does
(:func:`schlieren.workers.realistic.run_case`). Writes ``--work/labgap_LABEL.json`` (one row per
variant, appended).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import time
from pathlib import Path

FAMILY = Path("/work/realistic")


def _presets():
    from schlieren.pipeline.synthetic.lab import LAB_PRESETS, LabParams

    lab, alll = LAB_PRESETS["lab"], LAB_PRESETS["lab-all"]
    return {
        # leave one effect out of lab-all
        "lg-all-noroll": dataclasses.replace(alll, roll=0.0, roll_walk=0.0),
        "lg-all-noband": dataclasses.replace(alll, banding=0.0),
        "lg-all-novig": dataclasses.replace(alll, vignetting=0.0),
        "lg-all-nodefect": dataclasses.replace(alll, dead_pixels=0, stuck_pixels=0),
        "lg-all-nodefocus": dataclasses.replace(alll, defocus=0.0),
        # one effect of the lab preset alone
        "lg-defocus": LabParams(defocus=0.7),
        "lg-sharp": dataclasses.replace(lab, defocus=0.0),
        "lab": lab, "lab-all": alll,
    }


#: variant -> (family case it derives from, lab preset, reference frames)
VARIANTS = {
    "laball-16ref": ("plume2-16cam-640", "lab-all", 16),
    "laball-noroll": ("plume2-16cam-640", "lg-all-noroll", 3),
    "laball-noband": ("plume2-16cam-640", "lg-all-noband", 3),
    "laball-novig": ("plume2-16cam-640", "lg-all-novig", 3),
    "laball-nodefect": ("plume2-16cam-640", "lg-all-nodefect", 3),
    "laball-nodefocus": ("plume2-16cam-640", "lg-all-nodefocus", 3),
    "lab-3ref": ("plume2-16cam-640", "lab", 3),
    "p1-laball": ("plume1-16cam-640", "lab-all", 3),
    "p1-defocus": ("plume1-16cam-640", "lg-defocus", 16),
    "p1-sharp": ("plume1-16cam-640", "lg-sharp", 16),
    "turb5-defocus": ("turb5-16cam-640", "lg-defocus", 16),
    "turb5-sharp": ("turb5-16cam-640", "lg-sharp", 16),
    "coarse-defocus": ("plume2-16cam-640-coarse", "lg-defocus", 16),
}


def variant_case(name: str):
    from schlieren.pipeline.synthetic.lab import LAB_PRESETS
    from schlieren.workers.bench.realistic_cases import CASES

    base_name, preset, refs = VARIANTS[name]
    for k, v in _presets().items():
        LAB_PRESETS.setdefault(k, v)
    base = next(c for c in CASES if c.name == base_name)
    return dataclasses.replace(base, name=f"lg-{name}", lab=preset, reference_frames=refs), base


def _share_family(work: Path, base) -> None:
    """The CFD cache and the clean twin's stamp (its flow scale) from the family, read only."""
    work.mkdir(parents=True, exist_ok=True)
    if not (work / "_cfd").exists():
        os.symlink(FAMILY / "_cfd", work / "_cfd")
    stamp = work / base.name / "case.json"
    if not stamp.exists():
        stamp.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(FAMILY / base.name / "case.json", stamp)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/work/scratch-labgap")
    ap.add_argument("--variants", required=True)
    ap.add_argument("--params", default=None)
    ap.add_argument("--label", default="base")
    ap.add_argument("--keep", action="store_true", help="keep the stores (WORK/<variant>/store-LABEL.zarr)")
    a = ap.parse_args(argv)
    import yaml

    from schlieren.pipeline.stages import config_from_dict
    from schlieren.workers.realistic import run_case

    cfg = config_from_dict(yaml.safe_load(Path(a.params).read_text()) if a.params else None)
    work = Path(a.work)
    out = work / f"labgap_{a.label}.json"
    rows = json.loads(out.read_text()) if out.exists() else []
    for name in (v.strip() for v in a.variants.split(",") if v.strip()):
        case, base = variant_case(name)
        _share_family(work, base)
        t0 = time.perf_counter()
        res = run_case(case, work, config=cfg, label=a.label, truth_rows=False, keep_store=a.keep,
                       progress=lambda m: print(m, flush=True))
        of = res["rows"].get("optical_flow", {})
        row = {"variant": name, "base": base.name, "label": a.label, "params": a.params,
               "psnr": of.get("psnr"), "psnr_plume": of.get("psnr_plume"),
               "diagnostics": res.get("diagnostics"), "seconds": time.perf_counter() - t0}
        print(json.dumps({k: row[k] for k in ("variant", "psnr", "psnr_plume", "seconds")}), flush=True)
        rows.append(row)
        out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
