"""Training reconstructs a moving object where it is, at every time (docs/training.md).

The failure this guards against (docs/results.md, "fifth session"): the deformation field
collapsed into one displacement shared by every Gaussian, and trained models rendered close to a
blank image; the moving sphere was lost at the times far from the canonical one. Here a small
synthetic scene whose red sphere travels 1.7 m (5.7 radii) is trained with the project's recipe
in under a minute, then:

- at early and late times, inside the sphere's true silhouette (ray cast from the generator's
  scene description, not a training image), the render must beat a blank image by a margin;
- the field must move the sphere's Gaussians by at least half the sphere's motion, along it, and
  the still sphere's by under a fifth of it: one shared displacement cannot do both.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.config import build_config  # noqa: E402
from nehad.data.synth import orbit_camera_to_world, render_view, scene_objects  # noqa: E402
from nehad.data.synth import synthesize_scene  # noqa: E402
from nehad.runtime.cameras import Camera  # noqa: E402
from nehad.runtime.raster import render  # noqa: E402
from nehad.model import cloud_at, load_run  # noqa: E402
from nehad.trainer import Trainer  # noqa: E402

SIZE = 48
#: a small field and schedule with the recipe of the presets (time curriculum, standardised
#: trunk, softplus decoder): about 30 s on two cores
SETS = ["coarse.iterations=200", "fine.iterations=1400", "field.resolution=[24,24,24,16]",
        "field.out_dim=16", "field.multires=[1]", "field.width=32", "field.hnn_hidden=32",
        "densify.max_gaussians=3000", "train.init_random_points=1500", "train.sh_degree=1",
        "train.checkpoint_interval=100000", "train.log_interval=100"]


def _index(scene: str, name: str) -> int:
    return [o.name for o in scene_objects(scene, 0.0)].index(name)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("quality")
    data = synthesize_scene(root / "scene", "spheres", resolution=SIZE, frames=40, seed=5,
                            points=0)
    cfg = build_config("test", None, SETS)
    Trainer(cfg, data, root / "run", progress=False, log=None).train()
    return load_run(root / "run")


def _masked_psnr(img, ref, mask) -> float:
    mse = float(np.mean((np.clip(img, 0, 1)[mask] - ref[mask]) ** 2))
    return -10.0 * math.log10(max(mse, 1e-10))


@pytest.mark.slow
@pytest.mark.parametrize("t", [0.0, 0.1, 0.9, 1.0])
def test_the_moving_sphere_is_drawn_where_it_is(trained, t):
    model, meta = trained
    degree = meta.sh_degree
    focal = 0.5 * SIZE / math.tan(0.5 * math.radians(45.0))
    mover = _index("spheres", "mover")
    gains = []
    for azimuth in (0.3, 2.4, 4.4):  # cameras the training never saw exactly
        cam = Camera.from_camera_to_world(orbit_camera_to_world(azimuth, math.radians(35)),
                                          SIZE, SIZE, focal, focal, time=t)
        rgba, coverage = render_view(scene_objects("spheres", t), cam, supersample=3,
                                     return_coverage=True)
        truth = rgba[:, :, :3] + (1.0 - rgba[:, :, 3:])
        mask = coverage[:, :, mover] > 0.5
        assert mask.sum() > 20, "the sphere should be in view"
        pred = render(cloud_at(model, t, degree), cam, (1.0, 1.0, 1.0)).rgb
        blank = np.ones_like(truth)
        gains.append(_masked_psnr(pred, truth, mask) - _masked_psnr(blank, truth, mask))
    print(f"t = {t}: PSNR inside the moving sphere, gain over blank per camera: "
          f"{', '.join(f'{g:+.1f}' for g in gains)} dB")
    assert np.mean(gains) > 5.0, gains  # the time-bin target of issue 13; a collapse gives ~0


@pytest.mark.slow
def test_the_field_moves_the_mover_and_holds_the_still_sphere(trained):
    model, _ = trained
    g = model.gaussians
    with torch.no_grad():
        start = model.gaussians_at(0.0)[0].numpy()
        end = model.gaussians_at(1.0)[0].numpy()
        canon = g.means.numpy()
        opacity = torch.sigmoid(g.opacity_logits).numpy().reshape(-1)
    moved = end - start
    t_c = 0.5
    objects = {o.name: o for o in scene_objects("spheres", t_c)}

    def near(name: str) -> np.ndarray:
        o = objects[name]
        return (np.linalg.norm(canon - o.centre, axis=1) < o.radius + 0.05) & (opacity > 0.2)

    true_motion = scene_objects("spheres", 1.0)[_index("spheres", "mover")].centre - \
        scene_objects("spheres", 0.0)[_index("spheres", "mover")].centre
    on_mover, on_still = near("mover"), near("still")
    assert on_mover.sum() > 20 and on_still.sum() > 20
    mover_motion = np.median(moved[on_mover], axis=0)
    still_motion = np.median(np.linalg.norm(moved[on_still], axis=1))
    print(f"median displacement t=0 -> 1: mover {mover_motion.round(2)} (truth "
          f"{true_motion.round(2)}), still sphere {still_motion:.3f}")
    direction = true_motion / np.linalg.norm(true_motion)
    along = float(np.median(moved[on_mover] @ direction))
    print(f"  mover's displacement along its true motion: {along:.2f} of "
          f"{np.linalg.norm(true_motion):.2f} m")
    assert along > 0.5 * np.linalg.norm(true_motion)
    # a shared displacement would move the still sphere as far as the mover (1.69 m). With the
    # paper's BED masks holding it the figure was 0.09-0.11 m (2026-11-26, float32 rounding moves
    # it between runs); the recipe without them (2026-11-27, docs/design.md section 4.7) moves it
    # 0.17 m, 0.4 of its radius, while it still scores +13 to +29 dB over blank on its pixels at
    # t = 0, 0.5 and 1 from three unseen cameras (0.09 m and +9 to +26 dB with BED). The bound is
    # a fifth of the mover's motion: far from a collapse, not a hair above one run
    assert still_motion < 0.2 * np.linalg.norm(true_motion)
