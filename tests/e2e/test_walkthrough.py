"""docs/walkthrough.md ("bring your own rig") followed end to end, as a lab would.

The "lab capture" is the tiny synthetic session laid out like a real one: each camera a
folder of numbered PNGs that starts with frames of the bare background (recorded before
the plume), then the strobe flash and the plume; the calibration is one OpenCV
FileStorage YAML per camera (as OpenCV's calibration tools write it). The steps are the
walkthrough's commands: `schlieren init` (image sequences + imported calibration),
`schlieren run`, `schlieren evaluate` / `report --truth` (the synthetic capture has a
ground truth), then the store opened with xarray and written to netCDF.
"""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import yaml

BEFORE = 3  # background-only frames recorded before the plume


def lab_capture(tiny_session, root: Path) -> dict:
    """Image folders + OpenCV calibration files from the synthetic session; returns what init needs."""
    src = tiny_session.session.parent
    m = yaml.safe_load(tiny_session.session.read_text())
    (root / "calib").mkdir(parents=True)
    distances = []
    for c in m["cameras"]:
        name = c["name"]
        out = root / "capture" / name
        out.mkdir(parents=True)
        ref = src / c["reference"]
        for k in range(BEFORE):
            shutil.copy(ref, out / f"img{k}.png")
        frames = sorted((src / name / "frames").glob("*.png"))
        for k, f in enumerate(frames):
            shutil.copy(f, out / f"img{BEFORE + k}.png")  # natural order: img10 after img9
        fs = cv2.FileStorage(str(root / "calib" / f"{name}.yml"), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", int(c["image_size"][0]))
        fs.write("image_height", int(c["image_size"][1]))
        fs.write("camera_matrix", np.asarray(c["K"], np.float64))
        fs.write("distortion_coefficients", np.asarray(c["dist"], np.float64).reshape(1, -1))
        fs.write("R", np.asarray(c["R"], np.float64))
        fs.write("T", np.asarray(c["t"], np.float64).reshape(3, 1))
        fs.release()
        R, t = np.asarray(c["R"]), np.asarray(c["t"])
        centre, axis = -R.T @ t, R[2]
        p, n = np.asarray(c["background"]["point"]), np.asarray(c["background"]["normal"])
        distances.append(f"{name}={float((p - centre) @ n / (axis @ n)):.12g}")
    a, b = m["frames"]
    s0, s1 = m["sync"]["strobe"]["search_frames"]
    v = m["volume"]
    return {"frame_rate": m["frame_rate"], "line_time": m["cameras"][0]["rolling_shutter"]["line_time"],
            "frames": f"{a + BEFORE}:{b + BEFORE}", "strobe": f"{s0 + BEFORE}:{s1 + BEFORE}",
            "volume": ",".join(str(x) for x in v["min"] + v["max"]), "voxel_size": v["voxel_size"],
            "distances": distances, "cameras": [c["name"] for c in m["cameras"]]}


def test_walkthrough_with_image_sequences_and_an_opencv_calibration(tiny_session, tmp_path, capsys):
    import xarray as xr

    import schlieren
    from schlieren.workers.cli import main

    lab = lab_capture(tiny_session, tmp_path)
    session, store = tmp_path / "session", tmp_path / "run.zarr"

    # 1. init: one folder of images per camera, the OpenCV calibration files
    args = ["init", str(session), "--images"] + [str(tmp_path / "capture" / c) for c in lab["cameras"]]
    args += ["--calibration", str(tmp_path / "calib" / "*.yml"), "--reference-frames", f"0:{BEFORE}",
             "--frame-rate", str(lab["frame_rate"]), "--frames", lab["frames"], "--strobe-frames", lab["strobe"],
             "--line-time", str(lab["line_time"]), f"--volume={lab['volume']}",
             "--voxel-size", str(lab["voxel_size"])]
    for d in lab["distances"]:
        args += ["--background-distance", d]
    assert main(args) == 0, capsys.readouterr().err
    n_images = len(list((tmp_path / "capture" / lab["cameras"][0]).glob("*.png")))
    assert f"{len(lab['cameras'])} cameras, {n_images} frames at" in capsys.readouterr().out
    doc = yaml.safe_load((session / "session.yaml").read_text())
    assert doc["cameras"][0]["frames"].startswith("/") and doc["allow_external_paths"] is True

    # 2. run (serial here; --workers N on a workstation)
    assert main(["run", str(session), "--out", str(store), "--serial", "--no-progress"]) == 0

    # 3. accuracy against the synthetic ground truth, by capture frame index
    assert main(["evaluate", str(store), "--truth", str(tiny_session.truth), "--json", str(tmp_path / "acc.json")]) == 0
    acc = json.loads((tmp_path / "acc.json").read_text())
    a, b = (int(x) for x in lab["frames"].split(":"))
    assert [r["frame"] for r in acc["frames"]] == list(range(a, b))
    assert acc["overall"]["psnr"] > 30.0, acc["overall"]  # as the synthetic session's own run
    capsys.readouterr()
    assert main(["report", str(store), "--truth", str(tiny_session.truth), "--out", str(tmp_path / "report"),
                 "--cameras", "1"]) == 0
    html = (tmp_path / "report" / "index.html").read_text()
    assert "ground truth" in html and f"{acc['overall']['psnr']:.2f}"[:4] in html

    # 4. the store in xarray (default arguments, no warning) and netCDF
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = xr.open_zarr(store)
    assert list(ds["frame"].values) == list(range(a, b))
    ds.to_netcdf(tmp_path / "run.nc")
    back = xr.open_dataset(tmp_path / "run.nc")
    np.testing.assert_array_equal(back["temperature"].values, ds["temperature"].values)
    same = schlieren.open(store)
    assert float(same["temperature"].max()) == float(ds["temperature"].max()) > 293.0
