"""The realistic family's flows and cases (``schlieren bench realistic``).

A case is a capture: a CFD flow (:data:`FLOWS`), a rig, a format, and optionally a
background texture (:data:`TEXTURES`), a rolling-shutter readout and the lab effects of
:data:`~schlieren.pipeline.synthetic.lab.LAB_PRESETS`. Every case of the family comes in a
clean variant and a ``-lab`` variant, the same capture as a lab records it (the ``lab``
preset: camera shake against the reference, lamp flicker, defocus, hot pixels), so what
the lab effects cost is measured case by case (docs/realistic.md, "Lab captures").

Cases are ``tune`` (plume seed 1: defaults may be chosen on them) or ``report`` (every
other flow, texture and rig: nothing was chosen on them).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass

from schlieren.pipeline.synthetic.background import Texture
from schlieren.pipeline.synthetic.lab import LAB_PRESETS

__all__ = ["Flow", "FLOWS", "TEXTURES", "RealisticCase", "CASES", "BITRATE_CASES", "QUICK_CASES", "select_cases",
           "clean_twin", "BOX", "VOXEL", "CFD_T0", "CFD_KNOTS", "PAPER_TARGETS", "PAPER_OPTICAL_FLOW",
           "DEFAULT_LINE_TIME"]

#: (cameras, image size) -> (whole box dB, in plume dB) targets of issue 14, default parameters.
PAPER_TARGETS = {16: (40.0, 30.0), 8: (38.0, 28.0)}
#: The paper's Table 1 optical-flow row (dB) for the same camera counts.
PAPER_OPTICAL_FLOW = {16: 39.84, 8: 39.29}

BOX = ((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3))
VOXEL = 0.0025
CFD_T0 = -0.06       # session time of the first CFD knot (s): before any camera's first row
CFD_KNOTS = 40       # at 1/120 s: covers 12 processed frames
#: The rolling shutter's line time of the family's cameras unless a case sets its own (s).
DEFAULT_LINE_TIME = 1.54e-5


@dataclass(frozen=True)
class Flow:
    """One CFD flow of the family (kind, seed, source); ``None`` fields take
    :class:`~schlieren.pipeline.synthetic.cfd.CFDParams`' defaults."""

    name: str
    kind: str
    seed: int
    excess_temperature: float = 40.0
    source_radius: float = 0.015
    inflow_velocity: float = 0.15
    swirl: float = 0.5
    perturbation: float | None = None
    perturbation_scale: float | None = None
    perturbation_time: float | None = None
    spinup: float | None = None

    def params(self):
        from schlieren.pipeline.synthetic.cfd import CFDParams

        extra = {k: v for k, v in dataclasses.asdict(self).items()
                 if k in ("perturbation", "perturbation_scale", "perturbation_time", "spinup") and v is not None}
        return CFDParams(kind=self.kind, excess_temperature=self.excess_temperature,
                         source_radius=self.source_radius, inflow_velocity=self.inflow_velocity, swirl=self.swirl,
                         **extra)

    def key_dict(self) -> dict:
        """The fields that define the flow (the unset optional ones left out, so the keys of
        flows defined before they existed do not change)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


FLOWS = {
    "plume-s1": Flow("plume-s1", "plume", 1),
    "plume-s2": Flow("plume-s2", "plume", 2),
    "jet-s3": Flow("jet-s3", "jet", 3, excess_temperature=60.0, source_radius=0.006, inflow_velocity=1.2,
                   swirl=0.3),
    # a thin, slow, nearly laminar plume above a 5 mm source, gently swaying (a candle's)
    "candle-s4": Flow("candle-s4", "plume", 4, excess_temperature=80.0, source_radius=0.005, inflow_velocity=0.05,
                      swirl=0.15, perturbation=0.15, perturbation_time=0.2, spinup=1.0),
    # a wide plume driven hard: strong, fast, fine-grained source modulation and swirl
    "turb-s5": Flow("turb-s5", "plume", 5, excess_temperature=60.0, source_radius=0.02, inflow_velocity=0.4,
                    swirl=1.5, perturbation=0.8, perturbation_scale=0.005, perturbation_time=0.02),
}

#: Background textures of the variety cases (the family's default: Wavelet Noise, finest
#: spacing 1.5 px). ``fine``/``coarse``: the same noise at 1 and 3 px; ``dots``: a printed
#: random dot pattern, 4 px pitch, dots 2.4 px across.
TEXTURES = {
    "fine": Texture(kind="noise", scale=1.0),
    "coarse": Texture(kind="noise", scale=3.0),
    "dots": Texture(kind="dots", scale=4.0, dot_diameter=0.6, dot_edge=0.1),
}


@dataclass(frozen=True)
class RealisticCase:
    """One capture of the family.

    Attributes
    ----------
    name : str
    flow : str
        Key of :data:`FLOWS`.
    role : {"tune", "report"}
        Defaults may be chosen on ``tune`` cases only.
    cameras : int
        Half-ring cameras.
    size : (int, int)
        Image width, height.
    distortion : bool
        Mild radial/tangential lens distortion.
    video : str or None
        ``None``: 8-bit PNG frames; ``"h264"``: lossy video at :attr:`bits_per_pixel`.
    bits_per_pixel : float
        Video bit budget per pixel and frame (camcorder AVCHD: about 0.16).
    peak_px : float
        99.9th percentile of the deflection magnitude the flow is scaled to (pixels).
    frames : int
        Processed frames.
    noise : float
        Sensor noise (8-bit grey levels).
    reference_frames : int
        Noisy reference frames recorded per camera (averaged by the pipeline).
    voxel : float
        CFD grid, metres.
    upsample : int
        The CFD knots are cubic-spline upsampled this many times before rendering, and the
        truth is that field (:func:`~schlieren.pipeline.synthetic.cfd.upsample_cfd`); 1
        traces the CFD grid itself (the family's first renders: docs/realistic.md, "What a
        case is").
    manifest_voxel : bool
        Write ``voxel`` into the manifest; by default the manifest leaves it out, as a
        user would, and the pipeline chooses it from the cameras' pixel footprint.
    lab : str or None
        Key of :data:`~schlieren.pipeline.synthetic.lab.LAB_PRESETS`: the capture as a lab
        records it; None: clean.
    texture : str or None
        Key of :data:`TEXTURES`; None: the default Wavelet Noise.
    line_time : float or None
        Rolling-shutter line time (seconds); None: :data:`DEFAULT_LINE_TIME`.
    """

    name: str
    flow: str
    role: str
    cameras: int
    size: tuple[int, int]
    distortion: bool = False
    video: str | None = None
    bits_per_pixel: float = 0.16
    peak_px: float = 0.25
    frames: int = 3
    noise: float = 1.5
    reference_frames: int = 16
    voxel: float = VOXEL
    upsample: int = 2
    manifest_voxel: bool = False
    lab: str | None = None
    texture: str | None = None
    line_time: float | None = None

    @property
    def variant(self) -> str:
        """``"clean"`` or the lab preset's name."""
        return self.lab or "clean"

    def key(self) -> str:
        """Content hash of everything that changes the rendered session (the fields added
        after the family's first renders enter it only when set, so those renders stay valid)."""
        d = dataclasses.asdict(self)
        d.pop("role")
        for k in ("lab", "texture", "line_time"):
            if d[k] is None:
                d.pop(k)
        if self.lab is not None:
            d["lab"] = {"preset": self.lab, **dataclasses.asdict(LAB_PRESETS[self.lab])}
        if self.texture is not None:
            d["texture"] = dataclasses.asdict(TEXTURES[self.texture])
        d["flow"] = FLOWS[self.flow].key_dict()
        d["version"] = 1
        return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]


def _tag(flow: str) -> str:
    kind, seed = flow.split("-")
    return kind + seed[1:]


def _clean_cases() -> list[RealisticCase]:
    out = []
    for flow, role in (("plume-s1", "tune"), ("plume-s2", "report"), ("jet-s3", "report")):
        tag = _tag(flow)
        out += [
            RealisticCase(f"{tag}-16cam-640", flow, role, 16, (640, 480), peak_px=0.25),
            RealisticCase(f"{tag}-8cam-960-dist", flow, role, 8, (960, 720), distortion=True, peak_px=0.375),
            RealisticCase(f"{tag}-8cam-960-dist-h264", flow, role, 8, (960, 720), distortion=True, video="h264",
                          peak_px=0.375, reference_frames=30),
        ]
        if flow.startswith("plume"):  # a second lossy case per plume: the 16-camera rig in H.264,
            # whose weaker deflections (0.25 px) the codec hides more (masks.grow_factor was chosen on it)
            out.append(RealisticCase(f"{tag}-16cam-640-h264", flow, role, 16, (640, 480), video="h264",
                                     peak_px=0.25, reference_frames=30))
    # variety no default was chosen on (issue 33): two more flow regimes, other textures, and a
    # rolling shutter reading out for 95 % of the frame period (33 us x 480 rows = 15.8 ms)
    for flow in ("candle-s4", "turb-s5"):
        out.append(RealisticCase(f"{_tag(flow)}-16cam-640", flow, "report", 16, (640, 480), peak_px=0.25))
    for texture in ("fine", "coarse", "dots"):
        out.append(RealisticCase(f"plume2-16cam-640-{texture}", "plume-s2", "report", 16, (640, 480), peak_px=0.25,
                                 texture=texture))
    out.append(RealisticCase("plume2-16cam-640-longro", "plume-s2", "report", 16, (640, 480), peak_px=0.25,
                             line_time=3.3e-5))
    return out


def _cases() -> tuple[RealisticCase, ...]:
    out = []
    for c in _clean_cases():
        out += [c, dataclasses.replace(c, name=f"{c.name}-lab", lab="lab")]
    # every effect at once, and a reference of 3 frames instead of 16
    base = next(c for c in out if c.name == "plume2-16cam-640")
    out.append(dataclasses.replace(base, name="plume2-16cam-640-laball", lab="lab-all", reference_frames=3))
    return tuple(out)


CASES: tuple[RealisticCase, ...] = _cases()
#: Not in the default family; run by name (``--cases plume2-8cam-960-dist-h264-1bpp``): the
#: same captures as ``plume2-8cam-960-dist-h264`` at higher bitrates, to measure what a
#: better camcorder setting buys (docs/realistic.md, "Lossy video").
BITRATE_CASES: tuple[RealisticCase, ...] = tuple(
    RealisticCase(f"plume2-8cam-960-dist-h264-{tag}", "plume-s2", "report", 8, (960, 720), distortion=True,
                  video="h264", bits_per_pixel=bpp, peak_px=0.375, reference_frames=30)
    for tag, bpp in (("0.5bpp", 0.5), ("1bpp", 1.0)))
#: A small subset for tests: 4 cameras, 160x120, one frame, coarse voxels (no CFD needed).
QUICK_CASES: tuple[RealisticCase, ...] = (
    RealisticCase("quick-4cam-160", "plume-s1", "tune", 4, (160, 120), peak_px=0.25, frames=1,
                  reference_frames=4, voxel=0.005, upsample=1, manifest_voxel=True),
)
#: The quick case as a lab records it (run by name; tests).
QUICK_LAB_CASES: tuple[RealisticCase, ...] = tuple(
    dataclasses.replace(c, name=f"{c.name}-lab", lab="lab") for c in QUICK_CASES)


def select_cases(names: str | None, *, role: str | None = None, variant: str | None = None
                 ) -> tuple[RealisticCase, ...]:
    """Cases by comma-separated names or name prefixes (``None``: all), optionally one role
    and one variant (``"clean"``, or ``"lab"`` for every lab preset)."""
    pool = CASES + QUICK_CASES + QUICK_LAB_CASES + BITRATE_CASES
    if names:
        wanted = [n.strip() for n in names.split(",") if n.strip()]

        def matches(w):  # an exact name, else every case it prefixes
            exact = [c for c in pool if c.name == w]
            return exact or [c for c in pool if c.name.startswith(w)]

        hits = {c.name for w in wanted for c in matches(w)}
        sel = [c for c in pool if c.name in hits]
        missing = [w for w in wanted if not matches(w)]
        if missing:
            raise ValueError(f"unknown case(s) {missing}; known: {', '.join(c.name for c in pool)}")
    else:
        sel = list(CASES)
    if role:
        sel = [c for c in sel if c.role == role]
    if variant == "clean":
        sel = [c for c in sel if c.lab is None]
    elif variant == "lab":
        sel = [c for c in sel if c.lab is not None]
    return tuple(sel)


def clean_twin(case: RealisticCase) -> RealisticCase | None:
    """The clean case a lab case is the lab variant of (same flow, rig, texture and readout)."""
    if case.lab is None:
        return None
    pool = CASES + QUICK_CASES + BITRATE_CASES
    twin = dataclasses.replace(case, lab=None, reference_frames=case.reference_frames)
    for c in pool:
        if c.lab is None and dataclasses.replace(c, name=twin.name, role=twin.role,
                                                 reference_frames=twin.reference_frames) == twin:
            return c
    return None
