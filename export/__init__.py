"""Export of trained NeHaD fields to one self-contained ONNX file (docs/design.md section 7)."""
