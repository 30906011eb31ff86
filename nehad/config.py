"""Every training knob of nehad as typed dataclasses with documented defaults (SPEC section 5),
and the presets `paper`, `cpu` (default), `quick`, `test`, `hypernerf` and `dynerf`.

A run's config is: preset -> YAML file (`--config`) -> dotted overrides (`--set a.b=v`), each
applied on top of the previous one; the resolved config is saved in the run directory.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Literal

from nehad.configtools import ConfigError, from_dict, load_yaml, merge, parse_override
from nehad.field.config import FieldConfig


@dataclass
class DataConfig:
    background: tuple[float, float, float] | None = None  # None: white for RGBA D-NeRF data, black for RGB
    downscale: int = 1  # integer image downscale factor (2 = half resolution)
    # Train images with alpha over a new random background colour each step (3DGS's
    # --random_background). Over a fixed white background, semi-transparent white "fog" is free
    # wherever it covers white, and it hides the scene from cameras inside it (the MuJoCo close
    # cameras); a random colour makes every uncovered pixel count. Evaluation uses `background`.
    random_background: bool = True
    frame_stride: int = 1  # keep every n-th frame (DyNeRF: video frames 0, n, 2n, ...; D-NeRF
    # and HyperNeRF: every n-th image of each split); applies to training and evaluation alike
    train_split: str = "train"
    eval_split: str = "test"


@dataclass
class StageConfig:
    iterations: int = 3000  # optimisation steps of this stage
    batch_size: int = 1  # views per step; their losses are averaged


@dataclass
class OptimConfig:
    position_lr_init: float = 1.6e-4  # times the scene extent, decays exponentially ...
    position_lr_final: float = 1.6e-6  # ... to this (times extent) at the end of training
    sh_dc_lr: float = 2.5e-3
    sh_rest_lr_divisor: float = 20.0  # higher SH bands learn at sh_dc_lr / this
    opacity_lr: float = 0.05
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    grid_lr_init: float = 1.6e-3  # hex-plane planes, exponential decay ...
    grid_lr_final: float = 1.6e-4  # ... to this
    decoder_lr: float = 1e-3  # trunk, HNN scalar networks and adapters ...
    decoder_lr_final: float | None = None  # ... decaying exponentially to this (None: constant)
    t_eq_lr: float = 1e-3  # BED equilibrium times (mu_eq learns like positions)


@dataclass
class DensifyConfig:
    start: int = 500  # first fine... first iteration (of each stage) that densifies
    stop: int = 15000  # no densification after this iteration (per stage)
    interval: int = 100  # densify and prune every this many iterations
    grad_threshold: float = 2e-4  # mean view-space (NDC) gradient norm above which to densify
    min_opacity: float = 0.005  # prune below this opacity
    percent_dense: float = 0.01  # clone below / split above this fraction of the scene extent
    opacity_reset_interval: int = 3000  # reset opacities to 0.01 every this many iterations
    prune_interval: int = 8000  # D-NeRF: large-Gaussian pruning only every this many iterations
    max_screen_size: int = 20  # prune Gaussians larger than this (pixels) at prune_interval
    max_gaussians: int = 0  # 0 = no cap; otherwise densification stops adding past this count
    # (of trainable Gaussians: in a layered run, --lod-levels, it caps each layer on its own)


@dataclass
class LossConfig:
    ssim_weight: float = 0.2  # loss = (1 - w) L1 + w D-SSIM; the hex-plane regulariser weights
    # are field knobs (field.reg_plane_weight, field.reg_time_smoothness_weight, ...)


@dataclass
class TrainConfig:
    seed: int = 0
    sh_degree: int = 3  # maximum SH degree; it grows by one every sh_degree_interval
    sh_degree_interval: int = 1000
    init: Literal["auto", "points", "random"] = "auto"  # auto: the dataset's points if any
    init_random_points: int = 2000  # D-NeRF: random points in [-1.3, 1.3]^3
    init_max_points: int = 0  # 0 = all; else a random subset of the dataset's points this large
    checkpoint_interval: int = 1000  # iterations between checkpoints (and at each stage end)
    log_interval: int = 50  # iterations between metric log lines
    keep_checkpoints: int = 2  # how many recent checkpoints stay on disk


@dataclass
class LodConfig:
    """Layered progressive optimisation for streaming (SPEC 8, `nehad.lod`): layer 0 is trained
    (coarse + fine stages) at the lowest resolution, data.downscale * 2^(levels - 1); each further
    layer adds Gaussians trained at twice the previous resolution while the earlier layers stay
    frozen and the deformation field is shared."""

    levels: int = 1  # number of layers L; 1 = ordinary training (no layers)
    iterations: int = 0  # steps per enhancement layer; 0 = fine.iterations
    opacity_threshold: float = 0.02  # at each layer's end, its Gaussians below this opacity are
    # dropped: a higher threshold makes each layer smaller (fewer bytes, less detail)
    spawn_opacity: float = 0.05  # opacity of the Gaussians that seed an enhancement layer (one
    # child per Gaussian of the layers below, drawn from its parent, half its size)
    base_max_gaussians: int = 0  # cap on layer 0, the first download (0: densify.max_gaussians);
    # a small base layer beside large enhancement layers makes the first fetch a small share
    train_field: bool = False  # also train the shared field during enhancement layers (it then
    # changes how the frozen lower layers move: a layer-0-only render drifts from what it was)


@dataclass
class Config:
    preset: str = "cpu"
    data: DataConfig = dc_field(default_factory=DataConfig)
    field: FieldConfig = dc_field(default_factory=FieldConfig)
    coarse: StageConfig = dc_field(default_factory=lambda: StageConfig(iterations=3000))
    fine: StageConfig = dc_field(default_factory=lambda: StageConfig(iterations=20000))
    optim: OptimConfig = dc_field(default_factory=OptimConfig)
    densify: DensifyConfig = dc_field(default_factory=DensifyConfig)
    loss: LossConfig = dc_field(default_factory=LossConfig)
    train: TrainConfig = dc_field(default_factory=TrainConfig)
    lod: LodConfig = dc_field(default_factory=LodConfig)

    def validate(self) -> "Config":
        try:
            self.field.validate()
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(f"field.{e}") from None
        for name in ("coarse", "fine"):
            stage = getattr(self, name)
            if stage.iterations < 0:
                raise ConfigError(f"{name}.iterations: must be >= 0")
            if stage.batch_size < 1:
                raise ConfigError(f"{name}.batch_size: must be >= 1")
        if self.data.downscale < 1:
            raise ConfigError("data.downscale: must be >= 1")
        if self.data.frame_stride < 1:
            raise ConfigError("data.frame_stride: must be >= 1")
        if not 0 <= self.train.sh_degree <= 3:
            raise ConfigError("train.sh_degree: must be in 0..3")
        if self.densify.interval < 1:
            raise ConfigError("densify.interval: must be >= 1")
        if not 1 <= self.lod.levels <= 6:
            raise ConfigError("lod.levels: must be in 1..6")
        if self.lod.iterations < 0:
            raise ConfigError("lod.iterations: must be >= 0 (0 = fine.iterations)")
        if not 0.0 <= self.lod.opacity_threshold < 1.0:
            raise ConfigError("lod.opacity_threshold: must lie in [0, 1)")
        if self.lod.base_max_gaussians < 0:
            raise ConfigError("lod.base_max_gaussians: must be >= 0 (0 = densify.max_gaussians)")
        if not 0.0 < self.lod.spawn_opacity < 1.0:
            raise ConfigError("lod.spawn_opacity: must lie in (0, 1)")
        return self


def _paper() -> Config:
    """The paper's settings (SPEC section 5): full resolution, 3000 + 20000 iterations."""
    return Config(preset="paper")


def _cpu() -> Config:
    """Sized for a 2-core CPU (each MuJoCo scene at 400x400 in about 20 minutes or less): half
    resolution, a SHORT static (coarse) stage, a short fine stage and a Gaussian cap. The
    deformation field is the paper's (D-NeRF hex-plane, W=64, D=1).

    Why the coarse stage is short (docs/results.md): the MuJoCo objects move by several
    diameters, so a static fit converges to the mean image, in which they are absent, and prunes
    the Gaussians that could have followed them. At 100x100 on scene1 (2000 fine steps, 20k
    Gaussians) 100 static steps instead of 1000 gave 21.06 vs 20.48 dB test PSNR.
    """
    return Config(
        preset="cpu",
        data=DataConfig(downscale=2),
        coarse=StageConfig(iterations=100),
        fine=StageConfig(iterations=2000),
        densify=DensifyConfig(start=200, stop=1600, interval=100, opacity_reset_interval=3000,
                              prune_interval=3000, max_gaussians=12000),
        train=TrainConfig(sh_degree=3, sh_degree_interval=500, checkpoint_interval=500,
                          init_max_points=10000),
    )


def _test() -> Config:
    """Seconds, for tests: tiny images, a small hex-plane, a handful of iterations."""
    return Config(
        preset="test",
        data=DataConfig(downscale=1),
        field=dataclasses.replace(FieldConfig(), resolution=(8, 8, 8, 4), out_dim=8,
                                  multires=(1,), width=16, hnn_hidden=16),
        coarse=StageConfig(iterations=30),
        fine=StageConfig(iterations=40),
        densify=DensifyConfig(start=10, stop=60, interval=10, opacity_reset_interval=1000,
                              prune_interval=1000, max_gaussians=1500),
        train=TrainConfig(sh_degree=1, sh_degree_interval=20, init_random_points=500,
                          checkpoint_interval=20, log_interval=10),
    )


def _quick() -> Config:
    """A few minutes on a 2-core CPU for small scenes (the demo): a coarser hex-plane, short
    stages, at most 10k Gaussians."""
    return Config(
        preset="quick",
        field=dataclasses.replace(FieldConfig(), resolution=(32, 32, 32, 16)),
        # A short static stage, as in `cpu`: on the demo scene 100 + 1900 steps gave 19.46 dB
        # test PSNR where 500 + 1500 gave 17.11 (docs/results.md).
        coarse=StageConfig(iterations=100),
        fine=StageConfig(iterations=1900),
        densify=DensifyConfig(start=200, stop=1200, interval=100, opacity_reset_interval=3000,
                              prune_interval=3000, max_gaussians=10000),
        train=TrainConfig(sh_degree=1, sh_degree_interval=500, checkpoint_interval=500,
                          log_interval=50),
    )


def _hypernerf() -> Config:
    """The paper's recipe on HyperNeRF captures (SPEC section 5): hex-plane out_dim 16,
    [64, 64, 64, 150], multires [1, 2, 4], trunk W = 128; images from rgb/2x (536 x 960, the
    paper's resolution, as 4DGS reads them). Regulariser weights of 4DGS's
    arguments/hypernerf/default.py (plane TV 2e-4, time smoothness 1e-3, time L1 1e-4)."""
    return Config(
        preset="hypernerf",
        data=DataConfig(downscale=2),
        field=FieldConfig.preset("hypernerf", reg_plane_weight=2e-4,
                                 reg_time_smoothness_weight=1e-3, reg_time_l1_weight=1e-4),
    )


def _dynerf() -> Config:
    """The paper's recipe on DyNeRF videos (SPEC section 5): hex-plane out_dim 16,
    [64, 64, 64, 150], multires [1, 2], trunk W = 128, opacity and SH deformed as 4DGS does for
    DyNeRF (arguments/dynerf/default.py: no_do=False, no_dshs=False, and its regulariser weights);
    1352 x 1014 frames (the 2704 x 2028 videos halved, the paper's resolution). Every frame of
    every camera is held in memory as float32: on a CPU add --set data.frame_stride=N."""
    return Config(
        preset="dynerf",
        data=DataConfig(downscale=2),
        field=FieldConfig.preset("dynerf", deform_opacity_sh=True, reg_plane_weight=2e-4,
                                 reg_time_smoothness_weight=1e-3, reg_time_l1_weight=1e-4),
    )


PRESETS = {"paper": _paper, "cpu": _cpu, "quick": _quick, "test": _test,
           "hypernerf": _hypernerf, "dynerf": _dynerf}


def build_config(preset: str = "cpu", config_file=None, overrides=()) -> Config:
    """preset -> YAML file -> `a.b=v` overrides; validated."""
    if preset not in PRESETS:
        raise ConfigError(f"preset: unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    cfg = PRESETS[preset]()
    if config_file is not None:
        data = load_yaml(config_file)
        data.pop("preset", None)
        cfg = merge(cfg, data)
    for text in overrides:
        cfg = merge(cfg, parse_override(text))
    return cfg.validate()


def config_from_dict(data: dict) -> Config:
    """Rebuild a resolved config (as saved in a run directory)."""
    return from_dict(Config, data).validate()
