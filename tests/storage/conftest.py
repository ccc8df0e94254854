"""Fixtures for the storage tests: tiny valid capture sessions written to tmp_path.

``session_builder`` returns a :class:`SessionBuilder`; ``b.write()`` writes a valid
manifest and small PNG frames for a few cameras on a ring around the volume, looking at
its centre; tests then break one thing (``b.manifest[...] = ...``; ``b.save()``) and
expect a precise error.
"""

from __future__ import annotations

import copy
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml


def look_at(centre, target, up=(0.0, 0.0, 1.0)):
    """World->camera rotation and translation (OpenCV: x right, y down, z forward)."""
    centre = np.asarray(centre, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - centre
    f /= np.linalg.norm(f)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    R = np.stack([right, down, f])
    t = -R @ centre
    return R, t


class SessionBuilder:
    """Writes a valid session folder; tests mutate ``manifest`` and call ``save()``."""

    def __init__(self, root: Path, *, n_cameras: int = 3, n_frames: int = 6, size=(40, 30),
                 radius: float = 1.0, seed: int = 0):
        self.root = Path(root)
        self.n_cameras = n_cameras
        self.n_frames = n_frames
        self.size = tuple(size)
        self.radius = radius
        self.rng = np.random.default_rng(seed)
        self.frames: dict[str, np.ndarray] = {}
        self.references: dict[str, np.ndarray] = {}
        W, H = self.size
        f = 60.0
        self.K = [[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]]
        self.target = np.array([0.0, 0.0, 0.05])
        cams = []
        for i in range(n_cameras):
            a = 2 * np.pi * i / n_cameras
            C = self.target + radius * np.array([np.cos(a), np.sin(a), 0.1])
            R, t = look_at(C, self.target)
            cams.append({
                "name": f"cam{i:02d}",
                "frames": f"cam{i:02d}/frames/%05d.png",
                "reference": f"cam{i:02d}/reference.png",
                "image_size": [W, H],
                "K": copy.deepcopy(self.K),
                "dist": [0.0, 0.0, 0.0, 0.0, 0.0],
                "R": R.tolist(),
                "t": t.tolist(),
                "background": {"distance": 2.0 * radius},
                "rolling_shutter": {"line_time": 1e-5},
                "time_offset": 0.001 * i,
            })
        self.manifest = {
            "format": "schlieren-session/1",
            "name": "tiny",
            "frame_rate": 60.0,
            "volume": {"min": [-0.05, -0.05, 0.0], "max": [0.05, 0.05, 0.1], "voxel_size": 0.01},
            "medium": {"n_ambient": 1.00029, "T_ambient": 293.15, "p_ambient": 101325.0,
                       "gladstone_dale": 2.26e-4},
            "cameras": cams,
        }

    @property
    def path(self) -> Path:
        return self.root / "session.yaml"

    def write(self, *, first_index: int = 0, dtype=np.uint8) -> "SessionBuilder":
        """Write frames, references and the manifest."""
        W, H = self.size
        hi = 255 if dtype == np.uint8 else 65535
        for cam in self.manifest["cameras"]:
            name = cam["name"]
            d = self.root / name / "frames"
            d.mkdir(parents=True, exist_ok=True)
            stack = self.rng.integers(0, hi + 1, size=(self.n_frames, H, W)).astype(dtype)
            for k in range(self.n_frames):
                assert cv2.imwrite(str(d / f"{k + first_index:05d}.png"), stack[k])
            ref = self.rng.integers(0, hi + 1, size=(H, W)).astype(dtype)
            assert cv2.imwrite(str(self.root / name / "reference.png"), ref)
            self.frames[name] = stack
            self.references[name] = ref
        return self.save()

    def save(self, text: str | None = None) -> "SessionBuilder":
        self.root.mkdir(parents=True, exist_ok=True)
        self.path.write_text(text if text is not None else yaml.safe_dump(self.manifest, sort_keys=False))
        return self

    def camera(self, i: int) -> dict:
        return self.manifest["cameras"][i]

    def copy_manifest(self) -> dict:
        return copy.deepcopy(self.manifest)


@pytest.fixture
def session_builder(tmp_path) -> SessionBuilder:
    """A valid 3-camera, 6-frame session of 40x30 PNG frames, written to ``tmp_path/session``."""
    return SessionBuilder(tmp_path / "session").write()


@pytest.fixture
def look_at_fn():
    """The ``look_at(centre, target)`` helper, -> (R, t)."""
    return look_at


@pytest.fixture
def make_builder(tmp_path):
    """Factory: ``make_builder(name, **kwargs)`` -> unwritten SessionBuilder under tmp_path."""

    def make(name: str = "s", **kwargs) -> SessionBuilder:
        return SessionBuilder(tmp_path / name, **kwargs)

    return make
