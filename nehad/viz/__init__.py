"""Looking at what a NeHaD model learned (issue 8): Gaussian trajectories over time, the BED
static/dynamic split and its score against ground-truth object masks, line plots of training, and
a self-contained HTML report of a run.

    nehad.viz.plots         line plots and colour maps drawn with numpy + OpenCV (no matplotlib)
    nehad.viz.trajectories  Gaussian centres tracked over t, drawn as paths over a render; mp4
    nehad.viz.masks         BED weights 1 - M_pos per Gaussian, their render, dynamic fraction
                            over time, and the split's score against moving-object masks
    nehad.viz.report        `nehad report RUN -o report.html`

Nothing here imports torch at import time: the trajectory and plot code works on any source of
Gaussians (an exported .onnx model through onnxruntime included); the functions that need the
torch model (BED weights, the report) import it when called.
"""

from __future__ import annotations


class VizError(ValueError):
    """A visualisation cannot be made from the given input (the message names it)."""


__all__ = ["VizError"]
