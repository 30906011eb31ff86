"""Every labelled object drawn, scored per object (issue 25): a test-sized version of the stress
suite's occluder (a small sphere on a long loop that passes behind a large static wall).

The sphere is never created by today's recipe (docs/training.md, "Objects that are never
created"; carving, off in the recipe, creates it on the training views but it is not tracked to
the test times: docs/results.md, 2026-11-25), so its test is a strict expected failure: when a change draws it, the test passes, the
marker fails the suite, and the marker must go."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.slow  # trains a stress scene (about 20 s)

from nehad.config import build_config  # noqa: E402
from nehad.data.synth_stress import synthesize_stress_scene  # noqa: E402
from nehad.evaluate import evaluate_run  # noqa: E402
from nehad.trainer import Trainer  # noqa: E402

SETS = ["coarse.iterations=150", "fine.iterations=350", "densify.max_gaussians=3000",
        "train.init_max_points=2500", "train.checkpoint_interval=1000"]


@pytest.fixture(scope="module")
def occluder(tmp_path_factory):
    root = tmp_path_factory.mktemp("occ")
    data = synthesize_stress_scene(root / "scene", "occluder", resolution=128, frames=80,
                                   points=20000)
    Trainer(build_config("test", None, SETS), data, root / "run", progress=False).train()
    result = evaluate_run(root / "run", "test", data, lpips=False, write_renders=False,
                          progress=False)
    return {o["name"]: o for o in result["objects"]}


def _quarter_gains(obj):
    return [b["gain"] for b in obj["time_bins"] if b.get("gain") is not None]


def test_the_wall_is_drawn_at_every_time(occluder):
    gains = _quarter_gains(occluder["wall"])
    assert len(gains) == 4 and min(gains) >= 3.0, gains


@pytest.mark.xfail(strict=True, reason="the occluded sphere is never created "
                                        "(docs/training.md, 'Objects that are never created')")
def test_the_occluded_sphere_is_drawn_at_every_time(occluder):
    gains = _quarter_gains(occluder["sphere"])
    assert len(gains) >= 3, gains  # scored in most quarters (else it is too small to score)
    assert min(gains) >= 3.0, gains  # today: +0.00 to +0.11 dB in the four quarters
