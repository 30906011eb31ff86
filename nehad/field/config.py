"""Configuration of the NeHaD deformation field (docs/design.md sections 4 and 5).

Every knob of the field lives in :class:`FieldConfig`; defaults are the D-NeRF preset of the
paper / 4DGS where the paper gives a value, and docs/design.md's documented choice where it does not
(BED constants, `dt`, `phi_max`). `validate()` raises a ValueError that names the offending field.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Mapping

#: Smooth activations allowed in the scalar networks F1, F2 (docs/design.md section 4.3).
SMOOTH_ACTIVATIONS = ("tanh", "softplus", "silu")
DECODERS = ("hnn", "mlp")
HNN_GRAD_MODES = ("autograd", "closed_form", "fused")
SPATIAL_REGULARIZERS = ("tv", "second_order")


#: The most values a hex-plane may hold (2 GiB as float32): a config asking for more is refused
#: before anything is allocated (the paper's largest, HyperNeRF's, holds 7.4 M).
MAX_PLANE_VALUES = 5 * 10**8


@dataclass
class FieldConfig:
    """Hex-plane encoder + trunk + decoder (HNN or 4DGS MLP) + physics switches.

    Ablation switches (paper Tab. "ablation", docs/design.md section 4 last paragraph) each turn one NeHaD component
    off on its own; the formula used when a switch is off is documented in
    :class:`nehad.field.deformation.DeformationField`.
    """

    # ---------------- hex-plane encoder (docs/design.md section 4.1, 4DGS `kplanes_config`) ----------------
    out_dim: int = 32
    """Feature channels per plane (4DGS `output_coordinate_dim`; D-NeRF 32, HyperNeRF/DyNeRF 16)."""
    resolution: tuple[int, int, int, int] = (64, 64, 64, 25)
    """Base plane resolution (x, y, z, t). The time resolution is about half the number of
    timestamps (25..100 for D-NeRF, 150 for HyperNeRF/DyNeRF); it is NOT scaled by `multires`."""
    multires: tuple[int, ...] = (1, 2)
    """Spatial upsampling factors, one hex-plane per factor; features are concatenated, so the
    feature width is `out_dim * len(multires)` (D-NeRF (1, 2); HyperNeRF (1, 2, 4))."""
    plane_init_low: float = 0.1
    """Spatial planes are initialised U(plane_init_low, plane_init_high) (4DGS / K-Planes)."""
    plane_init_high: float = 0.5
    """Upper bound of the spatial-plane initialisation."""
    time_plane_init: float = 1.0
    """Constant initial value of the space-time planes (1: the product starts time-independent)."""
    spatial_regularizer: str = "tv"
    """Spatial-plane smoothness: "tv" (K-Planes / 4DGS-paper total variation, first differences
    along both axes) or "second_order" (what the 4DGS code computes under the name plane_tv:
    squared second differences along the plane's first axis)."""
    mipmap: bool = False
    """Scale-aware anisotropic mipmapping of the hex-plane lookups (docs/design.md section 8, paper appendix):
    each plane gets a 2x average-pooled pyramid and a Gaussian samples it trilinearly at a level
    set by its world-axis scales relative to the plane cells (`nehad.field.mipmap`). Off by
    default; present in training and in the exported graph alike."""
    mipmap_levels: int = 0
    """Most pyramid levels per scale with `mipmap` (0 = as many as the plane sizes allow)."""
    reg_plane_weight: float = 1e-3
    """Weight of the spatial-plane smoothness in `regularization_loss()`: 10x 4DGS's 1e-4
    (docs/design.md section 5). Smoother spatial planes deform neighbouring Gaussians alike, which keeps rigid
    objects from fraying: +0.9 dB on two MuJoCo scenes, two seeds each (docs/training.md)."""
    reg_time_smoothness_weight: float = 1e-2
    """Weight of the second-order time smoothness of the space-time planes (docs/design.md section 5)."""
    reg_time_l1_weight: float = 1e-4
    """Weight of the L1 distance of the space-time planes to 1 (docs/design.md section 5)."""

    # ---------------- trunk M (docs/design.md section 4.2) ----------------
    width: int = 64
    """W: latent width of h = M(f). Must be even: h = (q, p) with d = W/2 each (docs/design.md section 4.2).
    64 for D-NeRF, 128 for the real-world presets."""
    depth: int = 1
    """D: Linear(F, W) followed by (D-1) x [ReLU, Linear(W, W)]."""

    # ---------------- decoder (docs/design.md section 4.3-4.5) ----------------
    decoder: str = "hnn"
    """"hnn" (NeHaD) or "mlp" (the 4DGS baseline row of the ablation: per-attribute ReLU heads,
    mu + dmu, s + ds, r + dr; no BED, no Verlet, no rigidity clamp)."""
    hnn_hidden: int = 64
    """Hidden width of each scalar network F1, F2 (the paper gives none; our choice = W)."""
    hnn_depth: int = 2
    """Number of hidden (Linear + activation) layers of F1 and F2 before the Linear(hidden, 1)."""
    activation: str = "softplus"
    """Activation of F1, F2: "softplus" (default), "tanh" or "silu". NOT "relu": v = grad_h F
    of a ReLU network is piecewise constant in h (its Jacobian, the Hessian of F, is zero almost
    everywhere), so the loss on v would send no gradient to h and nothing upstream (planes, trunk)
    would learn through v."""
    hnn_init_gain: float = 3.0
    """Factor on the initial weights and biases of F1's and F2's hidden layers (after PyTorch's
    default initialisation). v = grad_h F varies with h only through the curvature of the
    activations; with the default scale their inputs stay in the near-linear range, so v starts
    out almost the same for every Gaussian (docs/training.md)."""
    hnn_quadratic: bool = True
    """Add a learned quadratic form to each scalar network, F(h) = net(h) + h^T S h / 2 (S a
    symmetric W x W matrix, zero at the start), so grad_h F = grad_h net(h) + S h: the kinetic
    term of a Hamiltonian H = p^T p / 2m + V(q), written for the latent h. Without it v is the
    gradient of a softplus network alone, bounded by its weights and varying with h only through
    its gates (docs/design.md section 4.3). On since 2026-11-27 (docs/results.md); false is the
    paper's decoder as written."""
    hnn_grad: str = "fused"
    """How grad_h F is computed: "fused" (default since 2026-11-26: the explicit formula of
    docs/design.md section 4.4 and its hand-written backward as one autograd Function whose
    element-wise work runs as Numba passes, `nehad.field.hnn_fused`; CPU float32/float64, once
    differentiable; elsewhere and in graph capture the closed form is used; the training step
    took some 40 ms less than with "closed_form", docs/performance.md), "closed_form" (the same
    formula written with torch ops, also what the ONNX export writes; ordinary first-order
    autograd trains through it) or "autograd"
    (`torch.autograd.grad(..., create_graph=True)`, a double backward). The same function and
    the same parameter gradients up to rounding (tests/test_field.py, tests/test_hnn_fused.py);
    closed form took 26% less CPU per field forward+backward at 10k Gaussians than autograd
    (docs/performance.md). Under `torch.inference_mode()` "autograd" uses the closed form."""
    hexplane_kernel: str = "numba"
    """"numba": on the CPU (float32 points and planes, no mipmapping, outside export) the
    hex-plane lookup and its backward, and the planes' regularisers (total variation, the
    time planes' smoothness and L1) with their gradients, run as Numba passes (nehad.field.hexplane_kernel, tested against grid_sample and
    autograd); "torch": `F.grid_sample` and autograd, the reference and the GPU path."""
    rotation_kernel: str = "numba"
    """"numba": on the CPU (float32 or float64, outside export) step 8's rigidity clamp,
    quaternion product and normalisation run as one Numba pass each way
    (nehad.field.rigidity_kernel, tested against the torch functions); "torch": those functions
    through autograd, the reference and the GPU path."""
    use_hnn: bool = True
    """False = "HNN off" ablation: the two scalar networks and their input gradients are replaced
    by two direct MLPs of the same hidden width/depth mapping h -> R^W, whose outputs take the
    roles of v_c and v_s (v = v_c + v_s); everything downstream (adapters, force, BED, rigidity)
    is unchanged. Only the curl-free / divergence-free structure is removed."""

    # ---------------- position Verlet (docs/design.md section 4.6) ----------------
    verlet: bool = True
    """Position Verlet mu~ = mu + dt dmu + dt^2/2 F; off: mu~ = mu + dt dmu (no force term)."""
    dt: float = 1.0
    """Integrator step. 1.0: with dt = 1/T the learnable displacement would shrink by the frame
    count and learn T times slower (docs/design.md section 4.6)."""

    # ---------------- Boltzmann equilibrium decomposition (docs/design.md section 4.7) ----------------
    bed_position: bool = False
    """Blend positions with M_pos; off: mu' = mu~ (equivalent to M_pos = 0). Off since
    2026-11-27: every reading of the mask measured cost 1.7-2.5 dB (docs/design.md section 4.7);
    true is the paper's BED."""
    bed_scale: bool = False
    """Blend log-scale offsets with M_scale; off: s' = s + ds (equivalent to M_scale = 0). Off
    with bed_position (docs/design.md section 4.7)."""
    bed_distance: str = "canonical"
    """What the spatial deviation dd = |x - mu_eq| / sigma_s of M_pos measures (the paper's
    mu_i is ambiguous, docs/design.md section 4.7): "canonical": x = the canonical mean mu (the
    appendix's symbols; mu_eq starts at mu, so the mask starts as a function of t - t_eq alone
    and holds every Gaussian still around t_eq); "deformed": x = mu~, the Verlet-integrated
    position at time t, so a Gaussian the field moves far from its equilibrium is deformed
    freely and one it barely moves is held static (the paper's "larger distances indicate ...
    more intense motion, hence more likely to be dynamic primitives")."""
    sigma_s_fraction: float = 0.1
    """sigma_s = sigma_s_fraction * scene extent (spatial sensitivity)."""
    sigma_t: float = 0.25
    """Temporal sensitivity (time is in [0, 1])."""
    beta: float = 1.0
    """Inverse temperature of the Boltzmann factor."""
    gamma: float = 0.05
    """The floor of the masks ("mask") or of the deformation they let through ("deformation"),
    as `bed_floor` says."""
    bed_floor: str = "mask"
    """What gamma floors (docs/design.md section 4.7). "mask": the paper's formula as written,
    M = (1 - gamma) exp(-beta E) + gamma in [gamma, 1], so a Gaussian at equilibrium (at t = t_eq
    while mu_eq = mu) is wholly held, 1 - M = 0; "deformation": the paper's stated purpose of
    gamma ("minimum dynamic responsiveness to prevent complete deactivation"), the blend weight
    1 - M in [gamma, 1], M = (1 - gamma) exp(-beta E)."""
    lam: float = 0.5
    """Space-time coupling lambda of E_st; |lam| < 1 keeps E_st >= 0 so masks stay <= 1."""
    norm_eps: float = 1e-12
    """eps of the safe norms sqrt(|x|^2 + eps) (BED distance, rigidity axis, normalisations)."""

    # ---------------- local rigidity (docs/design.md section 4.8) ----------------
    rigidity: bool = True
    """Clamp the rotation angle of the quaternion delta; off: r' = N(r (x) q) unclamped."""
    phi_max: float = math.pi
    """Maximum rotation angle per deformation, phi' = phi_max tanh(phi / phi_max)."""

    # ---------------- appearance (docs/design.md section 4.9) ----------------
    deform_opacity_sh: bool = False
    """Also deform opacity logits and SH coefficients (4DGS does for DyNeRF; off for D-NeRF):
    o' = o + A_o v, c' = c + A_c v (MLP decoder: extra heads). Not masked by BED."""
    sh_coeffs: int = 16
    """K, the SH coefficients per colour channel deformed when `deform_opacity_sh` (degree 3)."""

    # ------------------------------------------------------------------------------------------
    @property
    def feature_dim(self) -> int:
        """F, the hex-plane feature width = out_dim * len(multires)."""
        return self.out_dim * len(self.multires)

    def validate(self) -> "FieldConfig":
        """Check every field; raise ValueError naming the first invalid one. Returns self."""
        self._validate_encoder()
        self._validate_network()
        self._validate_switches()
        self._validate_physics()
        return self

    def _bad(self, name: str, why: str):
        raise ValueError(f"FieldConfig.{name} = {getattr(self, name)!r}: {why}")

    def _finite(self, name: str) -> float:
        """The value of field `name` as a float; ValueError unless it is a finite number."""
        v = getattr(self, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self._bad(name, "must be a finite number")
        return float(v)

    def _pos_int(self, name: str, minimum: int = 1) -> None:
        """ValueError unless field `name` is an integer >= `minimum`."""
        v = getattr(self, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
            self._bad(name, f"must be an integer >= {minimum}")

    def plane_values(self) -> int:
        """Values in the hex-plane: per multires level m, three spatial planes (r_i m x r_j m)
        and three space-time ones (r_i m x r_t), out_dim channels each."""
        x, y, z, t = (int(r) for r in self.resolution)
        return sum(self.out_dim * ((x * y + x * z + y * z) * m * m + (x + y + z) * m * t)
                   for m in self.multires)

    def _validate_encoder(self) -> None:
        """The hex-plane fields: sizes, initialisation and regularisers."""
        self._pos_int("out_dim")
        res = self.resolution
        if (not isinstance(res, (tuple, list)) or len(res) != 4
                or any(isinstance(r, bool) or not isinstance(r, int) or r < 2 for r in res)):
            self._bad("resolution", "must be 4 integers (x, y, z, t), each >= 2")
        mr = self.multires
        if (not isinstance(mr, (tuple, list)) or len(mr) == 0
                or any(isinstance(m, bool) or not isinstance(m, int) or m < 1 for m in mr)):
            self._bad("multires", "must be a non-empty list of integers >= 1")
        values = self.plane_values()
        if values > MAX_PLANE_VALUES:
            self._bad("resolution", f"with multires {list(mr)} and out_dim {self.out_dim} the "
                                    f"hex-plane would hold {values:.3g} values "
                                    f"({values * 4 / 2**30:.1f} GiB as float32, three times that "
                                    f"while training); at most {MAX_PLANE_VALUES:.0e}")
        lo, hi = self._finite("plane_init_low"), self._finite("plane_init_high")
        if not lo < hi:
            self._bad("plane_init_high", "must exceed plane_init_low")
        self._finite("time_plane_init")
        if self.spatial_regularizer not in SPATIAL_REGULARIZERS:
            self._bad("spatial_regularizer", f"must be one of {SPATIAL_REGULARIZERS}")
        for name in ("reg_plane_weight", "reg_time_smoothness_weight", "reg_time_l1_weight"):
            if self._finite(name) < 0:
                self._bad(name, "must be >= 0")

    def _validate_network(self) -> None:
        """The trunk, the decoder and the HNN: sizes, activation and kernels."""
        self._pos_int("width", 2)
        if self.width % 2:
            self._bad("width", "must be even (h = (q, p) with d = W/2)")
        self._pos_int("depth")
        if self.decoder not in DECODERS:
            self._bad("decoder", f"must be one of {DECODERS}")
        self._pos_int("hnn_hidden")
        self._pos_int("hnn_depth")
        if self.activation not in SMOOTH_ACTIVATIONS:
            why = f"must be one of {SMOOTH_ACTIVATIONS}"
            if self.activation == "relu":
                why += ("; ReLU makes grad_h F piecewise constant in h, so nothing upstream of "
                        "the HNN would learn through v")
            self._bad("activation", why)
        if self.hexplane_kernel not in ("numba", "torch"):
            self._bad("hexplane_kernel", "must be numba or torch")
        if self.rotation_kernel not in ("numba", "torch"):
            self._bad("rotation_kernel", "must be numba or torch")
        if self.hnn_grad not in HNN_GRAD_MODES:
            self._bad("hnn_grad", f"must be one of {HNN_GRAD_MODES}")
        if (isinstance(self.mipmap_levels, bool) or not isinstance(self.mipmap_levels, int)
                or self.mipmap_levels < 0):
            self._bad("mipmap_levels", "must be an integer >= 0 (0 = automatic)")

    def _validate_switches(self) -> None:
        """The on/off switches are bools."""
        for name in ("use_hnn", "hnn_quadratic", "verlet", "bed_position", "bed_scale", "rigidity",
                     "deform_opacity_sh", "mipmap"):
            if not isinstance(getattr(self, name), bool):
                self._bad(name, "must be a bool")

    def _validate_physics(self) -> None:
        """The integrator, BED, rigidity and appearance constants."""
        if self._finite("hnn_init_gain") <= 0:
            self._bad("hnn_init_gain", "must be > 0")
        if self._finite("dt") <= 0:
            self._bad("dt", "must be > 0")
        if self.bed_distance not in ("canonical", "deformed"):
            self._bad("bed_distance", "must be 'canonical' or 'deformed'")
        if self.bed_floor not in ("mask", "deformation"):
            self._bad("bed_floor", "must be 'mask' or 'deformation'")
        for name in ("sigma_s_fraction", "sigma_t", "beta"):
            if self._finite(name) <= 0:
                self._bad(name, "must be > 0")
        if not 0.0 <= self._finite("gamma") < 1.0:
            self._bad("gamma", "must lie in [0, 1)")
        if not abs(self._finite("lam")) < 1.0:
            self._bad("lam", "|lam| must be < 1 so that E_st >= 0 (masks <= 1)")
        if self._finite("norm_eps") <= 0:
            self._bad("norm_eps", "must be > 0")
        if not 0.0 < self._finite("phi_max") <= 2 * math.pi:
            self._bad("phi_max", "must lie in (0, 2 pi]")
        self._pos_int("sh_coeffs")

    # ------------------------------------------------------------------------------------------
    @classmethod
    def preset(cls, name: str, **overrides: Any) -> "FieldConfig":
        """4DGS hex-plane presets of docs/design.md section 5: "dnerf", "hypernerf", "dynerf"; `overrides` win."""
        presets = {
            "dnerf": dict(out_dim=32, resolution=(64, 64, 64, 25), multires=(1, 2), width=64),
            "hypernerf": dict(out_dim=16, resolution=(64, 64, 64, 150), multires=(1, 2, 4),
                              width=128),
            "dynerf": dict(out_dim=16, resolution=(64, 64, 64, 150), multires=(1, 2), width=128),
        }
        if name not in presets:
            raise ValueError(f"FieldConfig.preset: unknown preset {name!r}; one of {list(presets)}")
        return cls.from_dict({**presets[name], **overrides})

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "FieldConfig":
        """Build from a plain mapping (e.g. a resolved YAML config); lists become tuples.
        Unknown keys are an error naming the key. The result is validated."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"FieldConfig: unknown field(s) {unknown}")
        kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**kwargs).validate()

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (tuples as lists) for writing the resolved config."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}


__all__ = ["FieldConfig", "SMOOTH_ACTIVATIONS", "DECODERS", "HNN_GRAD_MODES",
           "SPATIAL_REGULARIZERS"]
