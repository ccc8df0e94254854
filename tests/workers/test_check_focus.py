"""``schlieren check`` on a uniformly defocused rig (issue 33): the same synthetic session
rendered in focus and with every camera's background 0.7 px out of focus (the lab
renderer's ``defocus``, recorded in its ``lab.json``). The focus column, relative to the
rig's best camera, cannot tell them apart; the predicted flow noise against what the
benchmark family's in-focus background gives at the same window can: the defocused rig
gets a lower expected accuracy and one note naming its cameras, the in-focus rig none."""

from __future__ import annotations

import re

import pytest

from schlieren.pipeline.synthetic.lab import LabParams
from schlieren.storage import synthetic_io as sio
from schlieren.workers.check import check_session, flow_noise_ratios, table_text, write_page
from schlieren.workers.synth import synthesize

SPEC = dict(cameras=2, phantom="blob", frames=1, size=(128, 96), seed=5, recon_voxel=0.01, supersample=2,
            reference_frames=8)


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    root = tmp_path_factory.mktemp("focus")
    out = {}
    for name, lab in (("in focus", None), ("defocused", LabParams(defocus=0.7))):
        d = synthesize(root / name.replace(" ", "_"), lab=lab, **SPEC).session.parent
        out[name] = (d, check_session(d))
    return out


def _expected(text: str) -> float:
    return float(re.search(r"expected in plume: ([0-9.]+) dB", text).group(1))


def test_a_uniformly_defocused_rig_is_flagged_and_expects_less(rigs, tmp_path):
    (sharp_dir, sharp), (soft_dir, soft) = rigs["in focus"], rigs["defocused"]
    if sharp.family is None or not sharp.family.flow_noise:
        pytest.skip("no benchmarks/results/check_family.json in this checkout")
    assert sio.read_lab_truth(soft_dir / "truth.zarr")["params"]["defocus"] == 0.7  # the ground truth
    # the focus column relative to the best camera: the same for both rigs
    assert [c.focus / max(x.focus for x in soft.checked) for c in soft.checked] == \
        pytest.approx([c.focus / max(x.focus for x in sharp.checked) for c in sharp.checked], abs=0.05)
    a, b = table_text(sharp), table_text(soft)
    # in focus: the flow noise is what the family's in-focus background gives (within 15 %)
    assert all(0.85 < r[0] < 1.15 and 0.85 < r[1] < 1.15 for r in flow_noise_ratios(sharp).values())
    assert "out of focus, or a weaker texture" not in a and "a noisier sensor" not in a
    # defocused: every camera's flow noise well above it, named in one line
    assert all(r[0] > 1.3 for r in flow_noise_ratios(soft).values())
    flagged = [line for line in b.splitlines() if "out of focus, or a weaker texture" in line]
    assert len(flagged) == 1 and flagged[0].strip().startswith("cam00, cam01: predicted flow noise"), b
    assert _expected(b) < _expected(a) - 0.3
    html = write_page(soft, tmp_path / "page").read_text()
    assert "cam00, cam01: predicted flow noise" in html
