"""MFGNet training side (PyTorch): network, losses, ModelNet40 protocol, training, evaluation."""
