"""Export of trained NeHaD fields to one self-contained ONNX file (SPEC section 7)."""
