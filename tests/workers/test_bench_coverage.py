"""The coverage benchmark's arithmetic (workers/bench/coverage.py) and its page."""

import numpy as np

from schlieren.pipeline.uncertainty import UncertaintyParams
from schlieren.workers.bench import coverage as cov
from schlieren.workers.bench.coverage_markdown import coverage_markdown


def test_coverage_of_gaussian_errors_by_their_sigma_is_the_gaussians():
    rng = np.random.default_rng(0)
    sigma = rng.uniform(0.5, 2.0, size=200_000)
    c = cov.coverage(rng.normal(size=sigma.size) * sigma, sigma, np.ones(sigma.size, bool))
    assert abs(c["within_1"] - 0.6827) < 0.005 and abs(c["within_2"] - 0.9545) < 0.003
    assert cov.coverage(sigma, sigma, np.zeros(sigma.size, bool))["voxels"] == 0


def test_terms_sigma_is_the_stages_combination_and_zero_outside_the_hull():
    shape = (3, 4, 5)
    terms = {"noise": np.full(shape, 3.0), "boundary": np.full(shape, 1.0), "structure": np.full(shape, 10.0)}
    hull = np.zeros(shape, bool)
    hull[1] = True
    p = UncertaintyParams(boundary_scale=4.0, structure_scale=0.0)
    s = cov.terms_sigma(terms, p, hull)
    assert np.allclose(s[hull], 5.0) and np.all(s[~hull] == 0)
    # the bias term in quadrature, with its scale (0 leaves it out)
    terms["bias"] = np.full(shape, 2.0)
    s = cov.terms_sigma(terms, UncertaintyParams(boundary_scale=4.0, structure_scale=0.0, bias_scale=6.0), hull)
    assert np.allclose(s[hull], 13.0) and np.all(s[~hull] == 0)
    s = cov.terms_sigma(terms, UncertaintyParams(boundary_scale=4.0, structure_scale=0.0, bias_scale=0.0), hull)
    assert np.allclose(s[hull], 5.0)


def test_coverage_page_keeps_tune_and_report_apart_and_says_how_sigma_was_made():
    pair = {"within_1": 0.7, "within_2": 0.95, "voxels": 10}
    row = {"pooled": {k: pair for k in ("plume", "plume_in_hull", "outside_in_hull", "outside_hull")},
           "noise_only": pair, "seconds_per_frame": {"tomography": 5.0}}
    out = {"command": "x", "label": "L", "from_terms": True, "samples": 8, "scales": "2,0.1", "load": (1, 1, 1),
           "cases": {"a": {**row, "role": "tune"}, "b": {**row, "role": "report"}}}
    page = coverage_markdown(out)
    assert "## Tune cases" in page and "## Report cases" in page and "scales 2,0.1" in page
    assert page.index("| a |") < page.index("## Report cases") < page.index("| b |")
    assert "| 5.0 | — |" in page
