"""Every training knob of nehad as typed dataclasses with documented defaults (docs/design.md section 5),
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


#: Most layers of the trunk (field.depth) or of each HNN net (field.hnn_depth).
MAX_LAYERS = 64
#: Most views of one training step (coarse/fine.batch_size).
MAX_BATCH_SIZE = 1024
#: Most weights of the deformation network (the hex-plane has its own bound, field/config.py).
MAX_NETWORK_VALUES = 5 * 10**8


def network_values(f: FieldConfig) -> int:
    """About how many weights the field's networks hold (an upper bound, docs/design.md section
    4.2): the trunk Linear(F, W) + (D - 1) Linear(W, W); the decoder, at most five MLP heads of
    Linear(W, W) or two HNN nets of Linear(W, H), (depth - 1) Linear(H, H), Linear(H, W); the
    adapters, Linear(W, 3K + 11) at most."""
    w, h = int(f.width), int(f.hnn_hidden)
    features = int(f.out_dim) * len(f.multires)
    trunk = (features + 1) * w + (int(f.depth) - 1) * (w + 1) * w
    heads = 5 * (w + 1) * (w + 48)
    hnn = 2 * ((w + 1) * h + (int(f.hnn_depth) - 1) * (h + 1) * h + (h + 1) * w)
    adapters = (w + 1) * 59
    return trunk + max(heads, hnn) + adapters


@dataclass
class DataConfig:
    background: tuple[float, float, float] | None = None  # None: white for RGBA D-NeRF data, black for RGB
    downscale: int = 1  # integer image downscale factor (2 = half resolution)
    # Train images with alpha over a new random background colour each step (3DGS's
    # --random_background) instead of the evaluation background. Off by default: when the alpha
    # of a surface differs between views (the MuJoCo floor is opaque white from the side cameras
    # and transparent from the top one), a random colour makes those targets contradict each
    # other, while over the evaluation background they agree (docs/training.md).
    random_background: bool = False
    # Resolution warm-up: (fraction of all training steps, extra downscale factor) pairs, in
    # order; from each fraction on, images are area-downscaled by that factor on top of
    # `downscale`. Early steps, where the Gaussians are large and blurry anyway, cost 1/4 or 1/16
    # as many pixels. () trains at `downscale` throughout.
    resolution_schedule: tuple[tuple[float, int], ...] = ()
    # The warm-up never takes an image's shorter side below this many pixels (a factor that
    # would is reduced): 400-pixel MuJoCo views warm up at 100, 100-pixel lego views not at all.
    warmup_min_size: int = 100
    frame_stride: int = 1  # keep every n-th frame (DyNeRF: video frames 0, n, 2n, ...; D-NeRF
    # and HyperNeRF: every n-th image of each split); applies to training and evaluation alike
    train_split: str = "train"
    eval_split: str = "test"


@dataclass
class StageConfig:
    """One training stage (coarse: static Gaussians; fine: the deformation field on). Schedules
    are fractions of the stage's `iterations`, so shortening or lengthening a stage keeps their
    meaning (docs/training.md)."""

    iterations: int = 3000  # optimisation steps of this stage
    batch_size: int = 1  # views per step; their losses are averaged
    densify_from: float = 0.025  # densify and prune from this fraction of the stage ...
    densify_until: float = 0.75  # ... until this one (3DGS: 500 and 15000 of 20000)
    opacity_reset_every: float = 0.15  # reset opacities every this fraction (3000 of 20000),
    # only inside the densification window (so never at the stage's end); 0 = never
    prune_large_every: float = 0.4  # also prune oversized Gaussians every this fraction, after
    # the first opacity reset (D-NeRF: 8000 of 20000); 0 = never
    prune_transparent: bool = True  # prune Gaussians under densify.min_opacity when densifying
    # Time curriculum (docs/training.md): a step draws only frames whose time lies within
    # `time_window` of train.canonical_time at the stage's start; the window widens linearly to
    # the whole time range by `window_growth` of the stage (0: it stays fixed). 1 = every frame.
    time_window: float = 1.0
    window_growth: float = 0.0
    # ... widened until it holds at least this many training frames (the nearest to its centre):
    # a monocular capture shows one camera per time, and the static stage needs viewpoints.
    # The MuJoCo captures hold 12-15 frames within 0.06 of t = 0.5; D-NeRF lego holds 6.
    min_window_frames: int = 12


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
    decoder_lr_final: float | None = 1e-4  # ... decaying exponentially to this over the fine
    # stage (None: constant). The paper gives 1e-3 and no decay; the decay to 1e-4 (4DGS decays
    # its deformation network 10x too) gained 1.0-2.3 dB on two MuJoCo scenes, two seeds each
    # (docs/training.md)
    t_eq_lr: float = 1e-3  # BED equilibrium times (mu_eq learns like positions)
    velocity_lr: float = 0.01  # straight-line velocities of carved Gaussians (scene extents
    # per unit of time; 0 for every other Gaussian)
    life_rate_lr: float = 0.5  # life rates k of carved Gaussians (k = 0 never moves: its
    # gradient is 0 there), in 1/time units; a carved Gaussian starts at k = 1 / carve.life


@dataclass
class DensifyConfig:
    """Adaptive density control of 3DGS; *when* it runs is each stage's schedule (StageConfig)."""

    interval: int = 100  # densify and prune every this many iterations
    grad_threshold: float = 2e-4  # mean view-space (NDC) gradient norm above which to densify
    min_opacity: float = 0.005  # prune below this opacity
    percent_dense: float = 0.01  # clone below / split above this fraction of the scene extent
    max_screen_size: int = 20  # prune Gaussians larger than this (pixels) when pruning large ones
    max_gaussians: int = 0  # 0 = no cap; otherwise densification stops adding past this count
    # (of trainable Gaussians: in a layered run, --lod-levels, it caps each layer on its own)


@dataclass
class CarveConfig:
    """Residual carving (nehad.carve, docs/training.md): Gaussians are added where the model
    does not draw what the views show. The recipe: one pass of the deforming stage that
    follows each unexplained blob through the views in time order and seeds a chain of
    Gaussians along its 3D path (`mode=tracks`; what the static stage never sees, such as an object
    behind an occluder around the canonical time, is otherwise never created)."""

    every: int = 0  # iterations between passes (inside each stage's densification window);
    # 0: the passes run at the fractions `at` instead
    at: tuple[float, ...] = (0.55,)  # with every = 0: the fractions of a stage's
    # iterations at which a pass runs (each moved past the part of an opacity-reset period
    # where opacities grow back: nehad.carve_pass.pass_iterations); (): no carving. One pass,
    # late, since 2026-11-29 (0.275 and 0.55 before): by then the field draws what it will,
    # so the unexplained blobs are the missing objects whole and their tracks land on them
    # (docs/training.md, "One tracks pass, late")
    views: int = 6  # "vote"/"rays": training views nearest in time to the pass's time
    mode: str = "tracks"  # "tracks": chains of Gaussians along the 3D paths of the unexplained
    # blobs through all the window's views (nehad.tracks); "vote": a point where the views
    # agree (nehad.carve.carve_points); "rays": seeds along every unexplained pixel's ray, the
    # optimisation picks the depth (nehad.carve.seed_rays)
    seed_views: int = 1  # "rays": the views nearest the pass's time that are seeded
    static_stage: bool = False  # passes in the static (coarse) stage too, at the canonical
    # time (their Gaussians live at every time); false: only in the deforming stage
    residual: float = 0.25  # a pixel is unexplained when render and target differ by more
    stride: int = 2  # one ray per stride x stride pixels
    depth_samples: int = 96  # samples per ray across the scene box
    min_views: int = 2  # a point must be in frame (and not hidden) in this many other views ...
    agree: float = 0.6  # ... and land near an unexplained pixel of its colour in this fraction
    colour_tol: float = 0.08  # largest chromaticity (rgb / sum) difference of the same surface
    motion: float = 1.5  # image widths per unit of time an object may move between the views
    opacity: float = 0.9  # opacity of a carved Gaussian (a chain's Gaussians start nearly
    # opaque: the few views that see each are far apart, and a faint start faded; the vote
    # and rays measurements of 2026-11-25 used 0.3)
    max_new: int = 1500  # Gaussians added per pass at most
    hold: bool = True  # a carved Gaussian's BED equilibrium is where it was seen (with
    # field.bed_position on, off in the recipe, the position mask holds it still around the
    # pass's time); false: its equilibrium is put out of reach
    # (M_pos = gamma), so the deformation field moves it from the start, as it moves anything
    # that is out of equilibrium
    track_width: float = 0.8  # "tracks": a seeded Gaussian's scale, in object radii
    max_tracks: int = 32  # "tracks": the most tracks one pass follows
    # (nehad.tracks.TrackSettings.max_tracks; 8 until 2026-11-28, a cap most passes reached,
    # which left the stress occluder's sphere without a chain over its first tenth of time:
    # docs/training.md, "How many tracks a pass follows")
    track_members: int = 1  # "tracks": Gaussians per seed, 1 or 7 (the seed's centre and six
    # points along its axes, each half its size: nehad.tracks.cluster_seeds)
    pin: bool = True  # Gaussians with a finite life keep the place, motion, time and life they
    # were given (nehad.carve_pass.pin_mortal: a view or two see each, which cannot place it
    # in depth); colour, opacity and shape are still learnt
    check_split: str = "val"  # "tracks": after training, each chain is kept only if it lowers the
    # error of this split's views around its times (nehad.chain_check.chain_lives); "" = off,
    # and nothing is checked when the data has no such split
    check_lives: tuple[float, ...] = (1.0, 1.5, 2.0, 3.0)  # then the lives of the kept chains'
    # trained members are multiplied by the one of these the split's views prefer
    # (nehad.chain_check.chain_lives): a chain Gaussian is trained by the views around its own
    # time, the held-out times see its neighbours' tails; (1.0,) = only keep or drop
    check_pieces: str = "chain"  # "chain": each chain is kept or dropped whole; "core": its
    # trained core (judged only by the held-out views between its first and last trained
    # member) and its two extrapolated ends each on its own (nehad.chain_check.core_and_ends)
    check_fill: bool = False  # before the check, each chain member no training view sees (at
    # a held-out time) takes the colour, opacity and shape of its chain's trained members
    # around its time (nehad.chain_check.fill_untrained); its place and motion stay the track's
    carry_steps: int = 1500  # "tracks", after the check: > 0 finds what the model draws only with
    # its chains as tracks again and fits each as one appearance carried along its track, this
    # many steps (nehad.carry, nehad.carry_stage); kept where the check split's views prefer it
    carry_members: int = 24  # Gaussians of one carried object (written out at every frame spacing)
    carry_min_blobs: int = 12  # shorter tracks are carried only as carry_absent_cover says
    carry_absent_cover: float = 0.3  # a shorter track is carried where the render (chains
    # hidden) covers its blobs less than this on the mean, or covers 3 of them less than this:
    # an object the model does not draw at all, not a texture it draws wrong
    # (nehad.carry_stage.carried_tracks); 0: never
    carry_knots: int = 1  # frame spacings between a carried object's written-out copies (each
    # lives as many spacings)
    carry_spin: bool = True  # also carry the moving objects whose blobs turn with a spin the
    # field does not follow (nehad.spin_tracks; docs/training.md, "Objects that spin")
    carry_texture_members: int = 128  # Gaussians of a carried round body whose spin is found in
    # its texture (nehad.texture_spin; written out at every copy): its texture is what shows
    # its turn (docs/training.md, "Round bodies: the spin in the texture")
    anchor_weight: float = 0.0  # "tracks": > 0 teaches the field each long track's path from a
    # point at its canonical-time place and adds Gaussians there (nehad.track_anchors); 0 off
    anchor_samples: int = 512  # (anchor, time) pairs of that loss a step
    anchor_min_blobs: int = 12  # tracks with fewer blobs are not anchored
    anchor_members: int = 7  # Gaussians added at each anchor (1 or 7: nehad.tracks.cluster_seeds)
    anchor_volume: float = 0.0  # the anchor loss's points uniform in a ball of this many object radii
    # about the anchor, each carried by the same offset (0: the anchor alone)
    anchor_cover: float = 0.0  # an anchor's Gaussians wait until its path (its track and the tracks
    # that continue it) covers this share of the training times' range
    anchor_release: bool = False  # an anchor's rows leave the loss once its Gaussians are added
    anchor_replace: bool = False  # with anchor_weight > 0: when an anchor's Gaussians are added,
    # the chain Gaussians on its track's path are removed, so the field's draw the object
    start: float = 0.0  # with every > 0: no pass before this fraction of a stage's iterations
    # (the model should first draw what it can, or its own errors make blobs)
    life: float = 1.0  # a carved Gaussian lives around its time: its opacity is scaled by
    # exp(-((t - t_c) / sigma)^2 / 2), sigma = life x the median spacing of the training times
    # (learnt after, unless pinned); 0 = it lives at every time (the vote and rays
    # measurements of 2026-11-25 used 3)


@dataclass
class LossConfig:
    ssim_weight: float = 0.2  # loss = (1 - w) L1 + w D-SSIM; the hex-plane regulariser weights
    # are field knobs (field.reg_plane_weight, field.reg_time_smoothness_weight, ...)
    kernel: str = "numba"  # "numba": the loss and its gradient in two fused Numba passes
    # (nehad.fused_loss, 3-4x faster on the CPU); "torch": the autograd reference
    # (nehad.losses), also used wherever the image is not one float32 CPU image
    isometry_weight: float = 0.0  # > 0: neighbouring Gaussians keep their distances at every
    # time in the deforming stage (nehad.isometry, docs/training.md; tried, not kept: 0 = off)
    isometry_neighbours: int = 8  # K nearest neighbours per Gaussian
    isometry_local_scale: bool = True  # each neighbourhood may grow or shrink as a whole
    isometry_reference: str = "canonical"  # the distances kept: the canonical Gaussians'
    # ("canonical") or the deformed ones' at the step that found the pairs ("time")
    isometry_refresh: int = 100  # steps between two searches for the pairs (it must divide
    # train.checkpoint_interval when the prior is on)
    acceleration_weight: float = 0.0  # > 0: each Gaussian's path bends little from one
    # training frame to the next, in the deforming stage (nehad.acceleration, docs/training.md)
    acceleration_samples: int = 1024  # Gaussians drawn each step for it
    acceleration_times: str = "view"  # where its paths are centred: the step's view's time
    # ("view") or a time drawn uniformly between the first and last training view ("uniform")
    scale_rate_weight: float = 0.0  # > 0: each Gaussian's size changes little from one
    # training frame step to the next, in the deforming stage (nehad.scale_rate,
    # docs/training.md "Gaussians that blink")
    scale_rate_samples: int = 1024  # Gaussians drawn each step for it
    scale_rate_times: str = "uniform"  # the pair of times compared: c drawn uniformly over the
    # training times and c + h, two field rows per sample ("uniform"), or the step's view's time
    # and one frame step before or after it, the view's own rows reused, one more row per sample
    # ("view")
    blur: float = 0.0  # > 0: in the deforming stage's first steps the render and its target
    # are both blurred before the loss, by a Gaussian of this share of the image width at the
    # stage's first step, shrinking linearly to none at `blur_until` of the stage, so that a
    # part that moves more than its own width between two training frames still pulls the
    # Gaussians of the frame before (docs/training.md, "Blurred early steps"; 0 = off)
    blur_until: float = 0.5  # share of the deforming stage at which the blur reaches 0
    eraser_weight: float = 0.0  # > 0: in the deforming stage each Gaussian of the background's
    # colour pays this much per unit of its opacity, so that the model does not trim an edge
    # for one camera with Gaussians that cut what passes behind them from the others
    # (nehad.erasers, docs/training.md "Erasers"; 0 = off)
    spin_weight: float = 0.0  # > 0: the deforming stage's tracks pass also searches the
    # training views for spinning bodies, and from then on the field's Gaussians on each turn
    # with it (nehad.spin_prior, docs/training.md "Objects that spin"; 0 = off)
    spin_samples: int = 256  # Gaussians of a body drawn each step for it


#: How `train.hold_mode` sets the held space-time rows (nehad.curriculum.hold_time_planes).
HOLD_MODES = ("value", "slope")


@dataclass
class TrainConfig:
    seed: int = 0
    sh_degree: int = 3  # maximum SH degree; it grows by one every sh_degree_interval
    sh_degree_interval: int = 1000
    init: Literal["auto", "points", "random"] = "auto"  # auto: the dataset's points if any
    init_random_points: int = 2000  # D-NeRF: random points in [-1.3, 1.3]^3
    init_max_points: int = 0  # 0 = all; else a random subset of the dataset's points this large
    # The time the canonical Gaussians show (docs/training.md): the coarse stage fits the frames
    # around it, the fine stage's time window grows from it, and the BED equilibrium times t_eq
    # start at it (paper Sec. "Boltzmann Equilibrium Decomposition").
    canonical_time: float = 0.5
    revive_opacity: float = 0.02  # at the static -> deforming boundary, opacities under this
    # are raised to it, so that the field can pull the static stage's half-seen Gaussians onto
    # their object before the first pruning (0 = off; docs/training.md, "Objects that are never
    # created")
    drift_window: float = 0.0  # W > 0: every Gaussian has a velocity v from the static stage on
    # and moves v clamp(t - t_eq, -W, W) after the field (0 = off: only carved Gaussians drift);
    # an experiment that did not create the objects the static stage misses (docs/training.md)
    # While the fine stage's time window is narrower than the time range, hold the space-time
    # planes outside it at the window's edge values, so a time that enters the window starts
    # from the deformation of its nearest trained time instead of the planes' initial value.
    hold_time_planes: bool = True
    # How the held rows are set (nehad.curriculum.hold_time_planes): "value", the edge row's;
    # "slope", the edge row carried on along its last step (a time entering the window starts
    # from its neighbours' motion continued, not stopped).
    hold_mode: str = "value"
    # At the start of the fine stage, rescale the trunk's first layer so that its output h has
    # mean 0 and standard deviation 1 over the Gaussians (DeformationField.standardize_trunk):
    # otherwise h, and with it the decoder's output, starts out the same for every Gaussian.
    standardize_trunk: bool = True
    # At the start of the fine stage, fit the hex-plane box to the canonical Gaussians (those
    # with opacity >= 0.1, 0.5-99.5 percentiles, padded by `fit_box_padding` of the box size on
    # each side) instead of keeping the initial points' bounds, which for a random initial
    # cloud can be much larger than the scene and waste the planes' cells.
    fit_box_to_gaussians: bool = True
    fit_box_padding: float = 0.15
    checkpoint_interval: int = 1000  # iterations between checkpoints (and at each stage end)
    log_interval: int = 50  # iterations between metric log lines
    keep_checkpoints: int = 2  # how many recent checkpoints stay on disk


@dataclass
class LodConfig:
    """Layered progressive optimisation for streaming (docs/design.md section 8, `nehad.lod`): layer 0 is trained
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


def coarse_stage(iterations: int, **overrides) -> StageConfig:
    """The static stage of the recipe (docs/training.md): only the frames within 0.06 of the
    canonical time, densified throughout, no opacity reset (one at the stage's end would hand
    the fine stage transparent Gaussians), and no pruning of transparent Gaussians: what the
    window half-sees (an object that moves across it) is kept for the deforming stage, which
    starts with every opacity raised to train.revive_opacity."""
    return StageConfig(**{**dict(iterations=iterations, densify_from=0.0, densify_until=1.0,
                                 opacity_reset_every=0.0, prune_large_every=0.0,
                                 time_window=0.06, window_growth=0.0,
                                 prune_transparent=False), **overrides})


def fine_stage(iterations: int, **overrides) -> StageConfig:
    """The deforming stage of the recipe (docs/training.md): the time window starts at 0.06
    around the canonical time and covers the whole range at half the stage; 3DGS densification
    from 10% to 80% of the stage with an opacity reset every 15%."""
    return StageConfig(**{**dict(iterations=iterations, densify_from=0.1, densify_until=0.8,
                                 opacity_reset_every=0.15, prune_large_every=0.0,
                                 time_window=0.06, window_growth=0.5), **overrides})


def _paper_coarse() -> StageConfig:
    return coarse_stage(3000, densify_from=0.17)  # 3DGS densifies from iteration 500


def _paper_fine() -> StageConfig:
    # 3DGS/4DGS: densify from 500 to 15000 of 20000, reset every 3000, D-NeRF large-Gaussian
    # pruning every 8000
    return fine_stage(20000, densify_from=0.025, densify_until=0.75, prune_large_every=0.4)


@dataclass
class Config:
    preset: str = "cpu"
    data: DataConfig = dc_field(default_factory=DataConfig)
    field: FieldConfig = dc_field(default_factory=FieldConfig)
    coarse: StageConfig = dc_field(default_factory=_paper_coarse)
    fine: StageConfig = dc_field(default_factory=_paper_fine)
    optim: OptimConfig = dc_field(default_factory=OptimConfig)
    densify: DensifyConfig = dc_field(default_factory=DensifyConfig)
    loss: LossConfig = dc_field(default_factory=LossConfig)
    carve: CarveConfig = dc_field(default_factory=CarveConfig)
    train: TrainConfig = dc_field(default_factory=TrainConfig)
    lod: LodConfig = dc_field(default_factory=LodConfig)

    def validate(self) -> "Config":
        self._validate_field()
        self._validate_stages()
        self._validate_choices()
        self._validate_resolution_schedule()
        self._validate_counts()
        self._validate_carve()
        self._validate_lod()
        self._check_ranges()
        return self

    def _validate_field(self) -> None:
        """The field's own checks, its messages prefixed with ``field.``; then the size of its
        network, before any of it is allocated."""
        try:
            self.field.validate()
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(f"field.{e}") from None
        self._validate_network_size()

    def _validate_network_size(self) -> None:
        """Refuse layer counts and widths that no CPU trains: `field.width=1e9` was a traceback
        of torch's allocator, `field.depth=1000000` spent minutes building a million layers."""
        f = self.field
        for key in ("depth", "hnn_depth"):
            if getattr(f, key) > MAX_LAYERS:
                raise ConfigError(f"field.{key}: {getattr(f, key)} layers; at most {MAX_LAYERS}")
        values = network_values(f)
        if values > MAX_NETWORK_VALUES:
            raise ConfigError(
                f"field.width ({f.width}), field.hnn_hidden ({f.hnn_hidden}): the deformation "
                f"network would hold about {values:.3g} weights ({values * 4 / 2**30:.1f} GiB as "
                f"float32, three times that while training); at most {MAX_NETWORK_VALUES:.0e}")

    def _validate_stages(self) -> None:
        """Iterations, batch sizes and the stage fractions of the coarse and fine stages."""
        for name in ("coarse", "fine"):
            stage = getattr(self, name)
            if stage.iterations < 0:
                raise ConfigError(f"{name}.iterations: must be >= 0")
            if not 1 <= stage.batch_size <= MAX_BATCH_SIZE:
                # each view of a step keeps its render graph until the backward pass: 10**9 asked
                # numpy for 8 GB of view indices and then drew for ever
                raise ConfigError(f"{name}.batch_size: must be in 1..{MAX_BATCH_SIZE}, got "
                                  f"{stage.batch_size}")
            for key in ("densify_from", "densify_until", "opacity_reset_every",
                        "prune_large_every", "window_growth"):
                if not 0.0 <= getattr(stage, key) <= 1.0:
                    raise ConfigError(f"{name}.{key}: must lie in [0, 1] (a fraction of the "
                                      f"stage)")
            if stage.densify_from > stage.densify_until:
                raise ConfigError(f"{name}.densify_from: must not exceed {name}.densify_until")
            if not 0.0 < stage.time_window <= 1.0:
                raise ConfigError(f"{name}.time_window: must lie in (0, 1] (1 = every frame)")

    def _validate_choices(self) -> None:
        """The canonical time and the named choices (loss kernel, carve mode)."""
        if not 0.0 <= self.train.canonical_time <= 1.0:
            raise ConfigError("train.canonical_time: must lie in [0, 1]")
        if self.loss.kernel not in ("numba", "torch"):
            raise ConfigError(f"loss.kernel: {self.loss.kernel!r}; expected numba or torch")
        for key in ("acceleration_times", "scale_rate_times"):  # the motion priors' times
            value = getattr(self.loss, key)
            if value not in ("view", "uniform"):
                raise ConfigError(f"loss.{key}: {value!r}; must be 'view' or 'uniform'")
        if self.loss.isometry_reference not in ("canonical", "time"):
            raise ConfigError(f"loss.isometry_reference: {self.loss.isometry_reference!r}; "
                              f"expected canonical or time")
        every, refresh = self.train.checkpoint_interval, self.loss.isometry_refresh
        if self.loss.isometry_weight > 0 and refresh > 0 and every % refresh:
            raise ConfigError(f"loss.isometry_refresh: {refresh} must divide "
                              f"train.checkpoint_interval ({every}), so that a resumed run "
                              f"finds the pairs where the uninterrupted one does")
        if self.train.hold_mode not in HOLD_MODES:
            raise ConfigError(f"train.hold_mode: must be one of {', '.join(HOLD_MODES)}, "
                              f"got {self.train.hold_mode!r}")
        if self.carve.mode not in ("vote", "rays", "tracks"):
            raise ConfigError(f"carve.mode: must be 'vote', 'rays' or 'tracks', got "
                              f"{self.carve.mode!r}")
        if self.carve.check_pieces not in ("chain", "core"):
            raise ConfigError(f"carve.check_pieces: must be 'chain' or 'core', got "
                              f"{self.carve.check_pieces!r}")

    def _validate_resolution_schedule(self) -> None:
        """Increasing fractions in [0, 1), factors >= 1."""
        last = -1.0
        for k, entry in enumerate(self.data.resolution_schedule):
            frac, factor = entry
            if not (0.0 <= frac < 1.0 and frac > last):
                raise ConfigError(f"data.resolution_schedule[{k}]: fractions must increase "
                                  f"within [0, 1)")
            if factor < 1:
                raise ConfigError(f"data.resolution_schedule[{k}]: the factor must be >= 1")
            last = frac

    def _validate_counts(self) -> None:
        """Sizes, strides and intervals of the data, stages, training and densification."""
        if self.data.warmup_min_size < 0:
            raise ConfigError("data.warmup_min_size: must be >= 0 (0 = no limit)")
        for name in ("coarse", "fine"):
            if getattr(self, name).min_window_frames < 0:
                raise ConfigError(f"{name}.min_window_frames: must be >= 0")
        if self.data.downscale < 1:
            raise ConfigError("data.downscale: must be >= 1")
        if self.data.frame_stride < 1:
            raise ConfigError("data.frame_stride: must be >= 1")
        if not 0 <= self.train.sh_degree <= 3:
            raise ConfigError("train.sh_degree: must be in 0..3")
        if self.densify.interval < 1:
            raise ConfigError("densify.interval: must be >= 1")

    def _validate_carve(self) -> None:
        """The carving counts and thresholds."""
        c = self.carve
        if c.every < 0 or c.views < 2 or c.stride < 1 or c.depth_samples < 1 or c.min_views < 1 \
                or c.max_new < 0:
            raise ConfigError("carve: every, max_new >= 0; views >= 2; stride, depth_samples, "
                              "min_views >= 1")
        if not (0.0 < c.residual < 1.0 and 0.0 < c.agree <= 1.0 and 0.0 < c.colour_tol <= 1.0
                and 0.0 < c.opacity < 1.0):
            raise ConfigError("carve: residual, opacity in (0, 1); agree, colour_tol in (0, 1]")
        if isinstance(c.max_tracks, bool) or not isinstance(c.max_tracks, int) or c.max_tracks < 1:
            raise ConfigError(f"carve.max_tracks: must be an integer >= 1, got {c.max_tracks!r}")
        if c.track_members not in (1, 7) or isinstance(c.track_members, bool):
            raise ConfigError(f"carve.track_members: must be 1 or 7, got {c.track_members!r}")
        if c.anchor_members not in (1, 7) or isinstance(c.anchor_members, bool):
            raise ConfigError(f"carve.anchor_members: must be 1 or 7, got {c.anchor_members!r}")
        if not all(isinstance(f, (int, float)) and 0.0 < f < 1.0 for f in c.at):
            raise ConfigError(f"carve.at: fractions of a stage in (0, 1), got {list(c.at)}")
        if not c.check_lives or not all(isinstance(f, (int, float)) and f >= 1.0
                                        for f in c.check_lives):
            raise ConfigError("carve.check_lives: one or more life factors >= 1, got "
                              f"{list(c.check_lives)}")

    def _validate_lod(self) -> None:
        """The level-of-detail settings."""
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

    #: (key, low, high): every other number a user sets, with the range it must lie in (None:
    #: unbounded on that side). Floats are finite already (configtools refuses nan and inf).
    RANGES = (
        ("optim.position_lr_init", 0.0, None), ("optim.position_lr_final", 0.0, None),
        ("optim.sh_dc_lr", 0.0, None), ("optim.opacity_lr", 0.0, None),
        ("optim.scaling_lr", 0.0, None), ("optim.rotation_lr", 0.0, None),
        ("optim.grid_lr_init", 0.0, None), ("optim.grid_lr_final", 0.0, None),
        ("optim.decoder_lr", 0.0, None), ("optim.decoder_lr_final", 0.0, None),
        ("optim.t_eq_lr", 0.0, None), ("optim.life_rate_lr", 0.0, None), ("optim.velocity_lr", 0.0, None), ("carve.life", 0.0, None), ("optim.sh_rest_lr_divisor", 1e-12, None),
        ("densify.grad_threshold", 0.0, None), ("densify.min_opacity", 0.0, 1.0),
        ("densify.percent_dense", 0.0, None), ("densify.max_screen_size", 0, None),
        ("densify.max_gaussians", 0, None), ("loss.ssim_weight", 0.0, 1.0),
        ("loss.isometry_weight", 0.0, None), ("loss.isometry_neighbours", 1, None),
        ("loss.isometry_refresh", 1, None), ("loss.acceleration_weight", 0.0, None),
        ("loss.acceleration_samples", 1, None), ("loss.scale_rate_weight", 0.0, None),
        ("loss.scale_rate_samples", 1, None),
        ("loss.eraser_weight", 0.0, None), ("loss.spin_weight", 0.0, None),
        ("loss.spin_samples", 1, None),
        ("loss.blur", 0.0, 0.25), ("loss.blur_until", 0.0, 1.0),
        ("carve.anchor_weight", 0.0, None),
        ("carve.anchor_samples", 1, None), ("carve.anchor_cover", 0.0, 1.0),
        ("carve.anchor_min_blobs", 1, None), ("carve.carry_steps", 0, None),
        ("carve.carry_members", 1, None), ("carve.carry_min_blobs", 1, None),
        ("carve.carry_knots", 1, None), ("carve.carry_texture_members", 1, None),
        ("train.sh_degree_interval", 0, None), ("train.init_random_points", 1, None),
        ("train.init_max_points", 0, None), ("train.fit_box_padding", 0.0, None),
        ("train.checkpoint_interval", 1, None), ("train.log_interval", 1, None),
        ("train.keep_checkpoints", 1, None), ("coarse.min_window_frames", 0, None),
        ("lod.base_max_gaussians", 0, None), ("carve.seed_views", 1, None),
        ("train.seed", 0, 2**32 - 1),  # numpy's generators take no negative seed
    )
    #: checked in configs built from a preset, a file and --set (`build_config`), not in a saved
    #: run's, which loaded before these checks were written
    NEW_RANGES = (("train.revive_opacity", 0.0, 0.99), ("train.drift_window", 0.0, None),
                  ("carve.carry_absent_cover", 0.0, 1.0))

    def _check_ranges(self, ranges=None) -> None:
        for key, low, high in self.RANGES if ranges is None else ranges:
            section, name = key.split(".")
            value = getattr(getattr(self, section), name)
            if value is None:
                continue
            if (low is not None and value < low) or (high is not None and value > high):
                if high is None:
                    want = "> 0" if 0 < low < 1e-6 else f">= {low}"
                else:
                    want = f"in [{low}, {high}]"
                raise ConfigError(f"{key}: must be {want}, got {value}")
        background = self.data.background
        if background is not None and not all(0.0 <= v <= 1.0 for v in background):
            raise ConfigError(f"data.background: each value must lie in [0, 1], got "
                              f"{list(background)}")


def _paper() -> Config:
    """The paper's settings (docs/design.md section 5): full resolution, 3000 + 20000 iterations, with the
    project's training recipe (docs/training.md)."""
    return Config(preset="paper")


def _cpu() -> Config:
    """Sized for a 2-core CPU: each MuJoCo scene at 400x400 in under 20 minutes (docs/results.md).
    The deformation field is the paper's (D-NeRF hex-plane, W = 64, D = 1) with one hidden
    layer per scalar network (`field.hnn_depth=1`: a 14% shorter step, the shared five within
    0.1 dB on the mean, docs/results.md); the schedule is
    shorter (1000 static + 12000 deforming steps), the first 40% of the steps see 100x100
    images and the next 30% 200x200 (data.resolution_schedule), and densification stops at 15k
    Gaussians. 2500 of the dataset's points start it (the MuJoCo `fused.ply` holds 100k random
    points). The slow-size prior is on (`loss.scale_rate_weight=0.1`, docs/training.md
    "Gaussians that blink"), and so is the prior against erasers (`loss.eraser_weight=2e-6`,
    docs/training.md "Erasers")."""
    return Config(
        preset="cpu",
        data=DataConfig(downscale=2, resolution_schedule=((0.0, 4), (0.4, 2), (0.7, 1))),
        field=dataclasses.replace(FieldConfig(), hnn_depth=1),
        coarse=coarse_stage(1000),
        fine=fine_stage(12000),
        densify=DensifyConfig(interval=100, max_gaussians=15000),
        train=TrainConfig(sh_degree=3, sh_degree_interval=1000, checkpoint_interval=1000,
                          init_max_points=2500),
        loss=LossConfig(scale_rate_weight=0.1, eraser_weight=2e-6),
    )


def _test() -> Config:
    """Seconds, for tests: tiny images, a small hex-plane, a handful of iterations."""
    return Config(
        preset="test",
        data=DataConfig(downscale=1),
        field=dataclasses.replace(FieldConfig(), resolution=(8, 8, 8, 4), out_dim=8,
                                  multires=(1,), width=16, hnn_hidden=16),
        coarse=coarse_stage(30, densify_from=0.3),
        fine=fine_stage(40, densify_from=0.25, densify_until=1.0, opacity_reset_every=0.0),
        densify=DensifyConfig(interval=10, max_gaussians=1500),
        train=TrainConfig(sh_degree=1, sh_degree_interval=20, init_random_points=500,
                          checkpoint_interval=20, log_interval=10),
    )


def _quick() -> Config:
    """A few minutes on a 2-core CPU for small scenes (the demo): a coarser hex-plane, short
    stages, at most 10k Gaussians."""
    return Config(
        preset="quick",
        field=dataclasses.replace(FieldConfig(), resolution=(32, 32, 32, 16)),
        coarse=coarse_stage(300),
        fine=fine_stage(3000),
        densify=DensifyConfig(interval=100, max_gaussians=10000),
        train=TrainConfig(sh_degree=1, sh_degree_interval=500, checkpoint_interval=500,
                          log_interval=50),
        # the carried objects' fit: its L1 is flat after a fifth of 500 steps on the demo's
        # bouncing ball, and 250 score the same (docs/results.md, 2026-11-30)
        carve=CarveConfig(carry_steps=250),
    )


def _hypernerf() -> Config:
    """The paper's recipe on HyperNeRF captures (docs/design.md section 5): hex-plane out_dim 16,
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
    """The paper's recipe on DyNeRF videos (docs/design.md section 5): hex-plane out_dim 16,
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


def build_config(preset: str | None = "cpu", config_file=None, overrides=()) -> Config:
    """preset -> YAML file -> `a.b=v` overrides; validated. `preset` None: the YAML file's own
    `preset:` (a run's config.yaml records it), else `cpu`; a preset given that differs from
    the file's is refused (the file's settings were made on its own)."""
    data = load_yaml(config_file) if config_file is not None else None
    named = data.pop("preset", None) if data is not None else None
    if preset is None:
        preset = named if named is not None else "cpu"
    elif named is not None and named != preset:
        raise ConfigError(f"{config_file}: preset {named!r}, but --preset {preset}: leave "
                          f"--preset out to use the file's, or remove its preset line")
    if preset not in PRESETS:
        raise ConfigError(f"preset: unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    cfg = PRESETS[preset]()
    if data is not None:
        cfg = merge(cfg, data)
    for text in overrides:
        change = parse_override(text)
        if "preset" in change:  # it would be recorded in config.yaml while the settings stay
            raise ConfigError(f"override {text!r}: the preset is chosen with --preset, not --set")
        cfg = merge(cfg, change)
    cfg.validate()
    cfg._check_ranges(Config.NEW_RANGES)
    return cfg


#: Keys whose default changed after runs had been saved without them: a saved config that lacks
#: one was trained with the value here (the default of its day), not today's default.
FORMER_DEFAULTS = {"field": {"hnn_quadratic": False}}  # the key came in 3230e51, on in 823ff3e


def config_from_dict(data: dict) -> Config:
    """Rebuild a resolved config (as saved in a run directory); a key it lacks takes the value
    the run trained with (FORMER_DEFAULTS, else today's default)."""
    if isinstance(data, dict):
        data = dict(data)
        for part, former in FORMER_DEFAULTS.items():
            if isinstance(data.get(part), dict):
                data[part] = {**former, **data[part]}
    return from_dict(Config, data).validate()
