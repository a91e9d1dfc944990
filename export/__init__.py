"""Training-side export: checkpoints -> ONNX graphs + manifest, parity checks, checkpoint importers."""

# Comparable pairs (not excluded as ties) whose final poses parity must compare: a fifth of the default 100 noise
# pairs, of which the bundled model with the most ties (clean) gives 50-54
# (docs/decisions/0061-parity-on-20-comparable-pairs.md). Here, not in export.parity, so that ``mfgnet export``'s
# options are read without importing torch.
MIN_COMPARED = 20
