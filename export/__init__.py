"""Training-side export: checkpoints -> ONNX graphs + manifest, parity checks, checkpoint importers."""
