"""NeHaD deformation field (docs/design.md section 4): hex-plane encoder, trunk, Hamiltonian decoder
(or the 4DGS MLP baseline), adapters, Boltzmann equilibrium masks, position Verlet and the
rotation rigidity clamp. Imports torch (training side only; `import nehad` stays torch-free)."""

from nehad.field.adapters import AdapterOutput, Adapters
from nehad.field.bed import bed_masks, position_mask, safe_norm, scale_mask
from nehad.field.config import FieldConfig
from nehad.field.deformation import DeformationField, DeformedGaussians, time_column
from nehad.field.hexplane import HexPlane, normalize_aabb
from nehad.field.hnn import (DirectFieldDecoder, FieldOutput, HamiltonianDecoder, ScalarNet,
                             activation_with_derivative, scalar_net_input_grad, symplectic)
from nehad.field.mlp_decoder import MLPHeads
from nehad.field.rigidity import (atan2_positive_y, clamp_rotation_delta, quat_multiply,
                                  rotation_angle, safe_normalize)
from nehad.field.trunk import Trunk

__all__ = [
    "FieldConfig", "DeformationField", "DeformedGaussians", "time_column",
    "HexPlane", "normalize_aabb", "Trunk",
    "ScalarNet", "scalar_net_input_grad", "activation_with_derivative", "symplectic",
    "HamiltonianDecoder", "DirectFieldDecoder", "FieldOutput",
    "Adapters", "AdapterOutput", "MLPHeads",
    "safe_norm", "position_mask", "scale_mask", "bed_masks",
    "quat_multiply", "safe_normalize", "atan2_positive_y", "clamp_rotation_delta",
    "rotation_angle",
]
