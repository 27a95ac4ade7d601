"""vtzero offline training: VQ-VAE tactile encoder, ONNX export, reference database."""
