"""Side-by-side comparisons of solid texture methods on one exemplar, or one per axis
(Dong 2008, 6.3-6.4; Kopf 2007). Each method runs in a fresh process so its time and peak
memory are its own; :class:`Setup` holds what they all run with (:mod:`.setup`),
:func:`compare` runs them (:mod:`.methods`, :mod:`.measure`) and :func:`write_report`
writes the sheet and tables (:mod:`.report`).

Methods: ``lazy`` (this project), ``kopf`` (Kopf et al. 2007 global optimization, plain
weighted averages), ``kopf-meanshift`` (the same with its mean-shift clustering, section 4.1),
``tiled`` (a 64^3 block of the lazy engine's texture, or its whole volume when smaller,
repeated, the usual practice of Dong 2008 Fig. 11, which repeats a periodic block: above 64
voxels these copies also meet at seams), and three references that are no solid texture:
``extrude`` (the z axis' exemplar stacked along z), ``noise`` (i.i.d. exemplar pixels) and
``flat`` (the exemplars' mean color everywhere, which shows what the neighbourhood energy
rewards, ``warptex.metrics``).

Each axis may have an exemplar of its own (Kopf 2007, section 6.2; Dong 2008, section 4), as
wood shows rings across its grain and streaks along it: the methods that synthesize read all
three, and the slices across an axis are measured against that axis' exemplar.

Timing: the median of ``repeats`` wall-clock runs per method (one by default), in a fresh
process, its Warp kernels compiled by a small run first. Kopf's seconds include its PCA and
search structures; the lazy engine's pre-computation of candidates (Dong 2008, section 4) is
computed afresh by the ``lazy`` method, not read from the cache, and timed apart
(``precompute_seconds``), as the paper reports both; ``tiled`` reads the same candidates from
the cache (computing them there when ``lazy`` is not compared).
"""

from warptex.compare.measure import compare
from warptex.compare.methods import (
    LARGE,
    METHOD_NOTES,
    METHODS,
    TILE,
    check_methods,
    large_edge,
    render_cube,
)
from warptex.compare.report import (
    REPORT_FILES,
    TABLE_FORMAT,
    report_files,
    run_line,
    run_summary,
    table_markdown,
    write_report,
)
from warptex.compare.setup import MIN_SIZE, Comparison, MethodResult, Setup

__all__ = [
    "LARGE",
    "METHODS",
    "METHOD_NOTES",
    "MIN_SIZE",
    "REPORT_FILES",
    "TABLE_FORMAT",
    "TILE",
    "Comparison",
    "MethodResult",
    "Setup",
    "check_methods",
    "compare",
    "large_edge",
    "render_cube",
    "report_files",
    "run_line",
    "run_summary",
    "table_markdown",
    "write_report",
]
