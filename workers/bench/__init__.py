"""``schlieren bench table1``: the paper's Table 1 (sec. 6) on the project's synthetic plume.

:mod:`.table1` renders, runs and scores the rigs and the Poisson-only bound;
:mod:`.markdown` writes the result as a page beside the paper's figures. The realistic
capture family (``schlieren bench realistic``) is :mod:`schlieren.workers.realistic`.
"""

from schlieren.workers.bench.markdown import table1_markdown
from schlieren.workers.bench.table1 import (DEFAULT_RIGS, PAPER_POISSON_BOUND, PAPER_TABLE1, QUICK_RIGS,
                                            Table1Config, bench_rig, bound_gradient, parse_rigs, poisson_bound,
                                            ref_rig, rig_failures, run_table1, truth_rows)

__all__ = ["Table1Config", "PAPER_TABLE1", "PAPER_POISSON_BOUND", "DEFAULT_RIGS", "QUICK_RIGS",
           "parse_rigs", "run_table1", "bench_rig", "truth_rows", "poisson_bound", "bound_gradient",
           "table1_markdown", "ref_rig", "rig_failures"]
